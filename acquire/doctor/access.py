"""The daemon's user, and whether a file's mode lets it read or write (``mls doctor`` often runs as
root or as the surveyor, while the daemon runs as ``mls`` with the supplementary group
``dialout``: systemd/mls-acquire.service ``User=``, ``SupplementaryGroups=``)."""

from __future__ import annotations

import grp
import os
import pwd
import stat
from dataclasses import dataclass

DAEMON_USER = "mls"
#: the unit's SupplementaryGroups=
UNIT_GROUPS = ("dialout",)
READ, WRITE = 4, 2


@dataclass(frozen=True, kw_only=True)
class DaemonUser:
    """Who the daemon runs as: ``installed`` False when the ``mls`` user does not exist here and
    the checks judge for the user running ``mls doctor`` instead."""

    name: str
    uid: int
    gids: frozenset[int]
    installed: bool

    @property
    def described(self) -> str:
        names = []
        for g in sorted(self.gids):
            try:
                names.append(grp.getgrgid(g).gr_name)
            except KeyError:
                names.append(str(g))
        return f"{self.name} (groups {', '.join(names)})"


def daemon_user(name: str = DAEMON_USER, unit_groups: tuple[str, ...] = UNIT_GROUPS) -> DaemonUser:
    """The daemon's user with its groups (its own, those listing it, the unit's); the current
    user when ``name`` does not exist."""
    try:
        pw = pwd.getpwnam(name)
    except KeyError:
        me = pwd.getpwuid(os.geteuid())
        return DaemonUser(
            name=me.pw_name, uid=me.pw_uid, gids=frozenset(os.getgroups()) | {os.getegid()}, installed=False
        )
    gids = {pw.pw_gid} | {g.gr_gid for g in grp.getgrall() if name in g.gr_mem}
    for g in unit_groups:
        try:
            gids.add(grp.getgrnam(g).gr_gid)
        except KeyError:
            pass
    return DaemonUser(name=name, uid=pw.pw_uid, gids=frozenset(gids), installed=True)


def may(st: os.stat_result, user: DaemonUser, want: int) -> bool:
    """Whether the mode bits of ``st`` grant ``user`` every bit of ``want`` (READ | WRITE);
    root may do anything."""
    if user.uid == 0:
        return True
    mode = stat.S_IMODE(st.st_mode)
    if st.st_uid == user.uid:
        bits = mode >> 6
    elif st.st_gid in user.gids:
        bits = mode >> 3
    else:
        bits = mode
    return bits & want == want


def describe(st: os.stat_result) -> str:
    """``crw-rw---- root:dialout``."""
    try:
        owner = pwd.getpwuid(st.st_uid).pw_name
    except KeyError:
        owner = str(st.st_uid)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    return f"{stat.filemode(st.st_mode)} {owner}:{group}"

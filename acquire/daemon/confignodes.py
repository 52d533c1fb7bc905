"""The checks of a vessel config's YAML nodes (:mod:`acquire.daemon.config`): :class:`Errors`
collects every error instead of stopping at the first, :func:`mapping_keys` reports each unknown
and missing key, :func:`variant` a mapping whose ``type`` says which keys it takes, and the value
checks (integers in a range, choices, names, paths, hosts) raise :class:`ConfigError`."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from calib.io.configfile import ConfigError, Node

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
#: the vessel name is a path component (``YYYYmmddTHHMMSSZ_<vessel>/``) and an MQTT topic level
#: (``<prefix>/<vessel>/…``): short enough for either with room to spare (a file name ≤ 255 bytes)
VESSEL_NAME_MAX_CHARS = 64
MS, US, NS_PER_S = 1_000_000, 1_000, 1_000_000_000


class Errors:
    """The errors found so far, one message each (validation goes on after an error)."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def get(self, fn: Callable[[], Any], default: Any = None) -> Any:
        """``fn()``, or ``default`` with its ConfigError recorded."""
        try:
            return fn()
        except ConfigError as e:
            self.add(str(e))
            return default


def mapping_keys(node: Node, errs: Errors, required=(), optional=()) -> dict[str, Node]:
    """The mapping's children; every unknown and every missing key is its own error."""
    if not isinstance(node.value, dict):
        errs.add(str(node.fail("a mapping")))
        return {}
    required, optional = set(required), set(optional)
    allowed = ", ".join(sorted(required | optional))
    for key in sorted(set(node.value) - required - optional):
        errs.add(f"{node.value[key].where()}: unknown key {key!r}; allowed keys here: {allowed}")
    for key in sorted(required - set(node.value)):
        errs.add(f"{node.where()}: missing required key {key!r}")
    return {k: v for k, v in node.value.items() if k in required | optional}


def int_between(node: Node, lo: int, hi: int) -> int:
    v = node.integer(minimum=lo)
    if v > hi:
        raise node.fail(f"an integer between {lo} and {hi}")
    return v


def choice(node: Node, choices) -> Any:
    if node.value not in choices or isinstance(node.value, bool):
        raise node.fail("one of " + ", ".join(str(c) for c in choices))
    return node.value


def valid_name(node: Node) -> str:
    v = node.string()
    if not NAME_RE.fullmatch(v):
        raise node.fail("a name of letters, digits, '_', '.', '-' (starting with a letter or digit)")
    return v


def vessel_name(node: Node) -> str:
    """The ``vessel``: a :func:`valid_name` of at most :data:`VESSEL_NAME_MAX_CHARS` characters."""
    v = valid_name(node)
    if len(v) > VESSEL_NAME_MAX_CHARS:
        raise node.fail(
            f"a name of at most {VESSEL_NAME_MAX_CHARS} characters (got {len(v)}): it names the "
            "session directories and the MQTT topics"
        )
    return v


def abs_path(node: Node) -> str:
    v = node.string()
    if not v.startswith("/"):
        raise node.fail("an absolute path (e.g. /dev/serial/by-id/...)")
    return v


def resolved_path(node: Node, base: Path) -> Path:
    p = Path(node.string()).expanduser()
    return p if p.is_absolute() else (base / p)


def host_name(node: Node) -> str:
    v = node.string()
    if any(c.isspace() for c in v) or "/" in v:
        raise node.fail("a host name or IP address")
    return v


def opt(m: dict[str, Node], key: str, errs: Errors, fn: Callable[[Node], Any], default: Any) -> Any:
    return errs.get(lambda: fn(m[key]), default) if key in m else default


def variant(
    node: Node,
    errs: Errors,
    what: str,
    choices,
    variants: Mapping[str, tuple[tuple[str, ...], tuple[str, ...]]],
):
    """A mapping whose ``type`` says which keys it needs (and which it may have). Returns
    ``(type, children)``, or None after recording every unknown and every missing key."""
    optional = {k for need, extra in variants.values() for k in need + extra}
    m = mapping_keys(node, errs, required={"type"}, optional=optional)
    t = errs.get(lambda: choice(m["type"], choices)) if "type" in m else None
    if t is None:
        return None
    need, extra = variants[t]
    allowed = {"type", *need, *extra}
    for key in sorted(set(m) - allowed):
        errs.add(f"{m[key].where()}: not a key of a {t} {what}; allowed: {', '.join(sorted(allowed))}")
    missing = [k for k in need if k not in m]
    for key in missing:
        errs.add(f"{node.where()}: missing required key {key!r} for a {t} {what}")
    return None if missing else (t, m)

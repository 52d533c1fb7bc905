"""Where the commands write: output directories and files named on the command line.

Writers never overwrite data silently. Every command that writes into a directory
(``mls sim dataset --out``, ``mls export --bundle`` and ``--laz``, ``mls calib run --out``,
``mls calib georef --out``, ``mls calib assess --out``, ``mls design --out``) checks it with
:func:`check_output_dir` before it computes anything:

- a path that exists and is not a directory is refused (``--out FILE``);
- a directory that already holds something is refused unless the command got ``--force``
  (then the command writes its files into it, replacing those of the same names);
- a missing directory is fine: :func:`make_output_dir` creates it (and its parents) when the
  command writes.

While it writes, a command holds the directory's writer lock (:func:`lock_output_dir`,
:mod:`calib.io.dirlock`): a second writer into the same directory is refused, ``--force`` or not.
The lock file ``.mls-lock`` does not count as content (a killed writer leaves it behind).

A file output (``mls export --sbet FILE``) is checked by :func:`check_output_file`: a directory
there is refused, an existing file only replaced with ``--force``. Each refusal is one line
naming the path and the option (:class:`OutputError`).

``mls demo`` is the one exception, on purpose: its run directory is its own (a marker file
``.mls-demo``), and it empties it at every start so that it can run twice in a row
(:func:`office.jobs.demo.prepare_out`); a directory it did not make is refused.
"""

from __future__ import annotations

from pathlib import Path

from calib.core.errors import CalibError
from calib.io.dirlock import LOCK_NAME, DirLock, hold


class OutputError(CalibError, ValueError):
    """An output path cannot be written as asked (the message names it and the option)."""


def _listing(entries: list[Path]) -> str:
    names = sorted(p.name for p in entries)
    more = f", … ({len(names)} entries)" if len(names) > 3 else ""
    return ", ".join(names[:3]) + more


def check_output_dir(path: str | Path, option: str = "--out", force: bool = False) -> Path:
    """``path`` as an output directory for ``option``: refused when it is a file, or when it
    already holds something and ``force`` is false (module docstring). Creates nothing."""
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: {option} names a directory, but this is a file")
    if d.is_dir() and not force:
        try:
            entries = [e for e in d.iterdir() if e.name != LOCK_NAME]
        except OSError as e:
            raise OutputError(f"{d}: {option}: cannot read the directory ({e.strerror or e})") from None
        if entries:
            raise OutputError(
                f"{d}: {option} is not empty ({_listing(entries)}); add --force to write into it "
                f"anyway (files of the same names are replaced), or choose a new directory"
            )
    return d


def make_output_dir(path: str | Path, option: str = "--out") -> Path:
    """Create the output directory ``path`` (and its parents); one line when it cannot be."""
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: {option} names a directory, but this is a file")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{d}: {option}: cannot create the directory ({e.strerror or e})") from None
    return d


def lock_output_dir(
    path: str | Path, option: str = "--out", force: bool = False, command: str | None = None
) -> DirLock:
    """``path`` checked (:func:`check_output_dir`), created and locked for this writer, then
    checked again under the lock (another writer may have finished meanwhile). The caller
    releases the returned :class:`DirLock` when it is done (or ends: the kernel releases it);
    :class:`calib.io.dirlock.OutputLocked` when another writer holds it."""
    d = check_output_dir(path, option, force)
    created = not d.exists()
    make_output_dir(d, option)
    lock = DirLock(d, command)
    lock.remove_dir_if_empty = created
    lock.acquire()
    try:
        check_output_dir(d, option, force)
    except BaseException:
        lock.release()
        raise
    return lock


def hold_output_dir(
    path: str | Path, option: str = "--out", force: bool = False, command: str | None = None
) -> DirLock:
    """:func:`lock_output_dir` for a command of the ``mls`` CLI: the lock is kept until the
    command ends (:func:`calib.io.dirlock.release_held`, called by the ``mls`` group)."""
    return hold(lock_output_dir(path, option, force, command))


def check_output_file(path: str | Path, option: str, force: bool = False) -> Path:
    """``path`` as an output file for ``option``: a directory there is refused, an existing file
    unless ``force``."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{p}: {option} names a file, but this is a directory")
    if p.exists() and not force:
        raise OutputError(f"{p}: {option}: the file exists; add --force to replace it")
    return p

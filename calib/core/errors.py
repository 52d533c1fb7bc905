"""The root of the project's one error tree (docs/architecture.md §9).

Every error that marine-mls raises on purpose derives from :class:`MlsError`, through one base
per layer: :class:`CalibError` here for ``calib``, :class:`ConfigError` for every configuration
file (site, scenario, vessel, faults), ``drivers.base.DriverError``,
``sim_devices.errors.SimDevicesError`` and ``acquire.errors.AcquireError``. The message of an
:class:`MlsError` is written for the operator: it names the file, line and field at fault, so the
CLI prints it as it is, once, without a traceback.

The tree lives at the bottom of the import graph (``calib.core``) so that every layer can
derive from it. The concrete classes keep the builtin exception they always were
(``ValueError`` for bad input, ``RuntimeError`` for a failed operation) as a second base.

:func:`read_file` is the one mapping of a failed file read (missing, a directory, permission, an
I/O error) to such a one-line message naming the file.
"""

from __future__ import annotations

from pathlib import Path


class MlsError(Exception):
    """An error marine-mls raises on purpose, with a message meant for the operator."""


class ConfigError(MlsError, ValueError):
    """A configuration file is invalid; the message names file:line:column and the field."""


class CalibError(MlsError):
    """Base of the errors of the calibration library (``calib``)."""


def read_file(
    path: Path, error: type[MlsError], *, expected: str = "a file", max_bytes: int | None = None
) -> bytes:
    """The bytes of the file ``path`` (at most ``max_bytes`` + 1 of them when bounded, so that the
    caller can tell a file too large), or ``error`` with one line naming the file:
    ``<path>: file not found``, ``<path>: is a directory, expected <expected>`` or
    ``<path>: cannot read (<reason>)`` (permission refused, an I/O error, …).

    The one mapping of a failed read for the readers of ``calib.io`` (configuration files,
    bundle CSVs, SBET records); decoding the bytes, and its message, stay with the format."""
    try:
        with path.open("rb") as f:
            return f.read() if max_bytes is None else f.read(max_bytes + 1)
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, expected {expected}") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e})") from None

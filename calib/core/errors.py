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
"""

from __future__ import annotations


class MlsError(Exception):
    """An error marine-mls raises on purpose, with a message meant for the operator."""


class ConfigError(MlsError, ValueError):
    """A configuration file is invalid; the message names file:line:column and the field."""


class CalibError(MlsError):
    """Base of the errors of the calibration library (``calib``)."""

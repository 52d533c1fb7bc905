"""The base of the errors the simulated devices raise on purpose (docs/architecture.md §9)."""

from __future__ import annotations

from calib.core.errors import MlsError


class SimDevicesError(MlsError, RuntimeError):
    """Base of the errors of ``sim_devices``, raised as is when the emulators cannot run as asked
    (the message says which device and why); ``RuntimeError`` as before."""

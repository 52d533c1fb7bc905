"""The base of the errors the acquisition side raises on purpose (docs/architecture.md §9)."""

from __future__ import annotations

from calib.core.errors import MlsError


class AcquireError(MlsError):
    """Base of the errors of ``acquire``: start-up, session log, export, guidance, demo. Each
    subclass keeps its builtin (``ValueError`` for bad input, ``RuntimeError`` for a failed
    operation) as a second base."""

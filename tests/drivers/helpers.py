"""Shared helpers for the driver tests: the real captures in ``tests/data/real`` (see its README)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

#: real device captures shipped with the tests (licences and provenance beside them)
REAL = Path(__file__).resolve().parents[1] / "data" / "real"

#: hypothesis settings for the decoder properties (the folder must stay fast on 2 cores)
PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def real_file(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_file():
        pytest.fail(f"real capture {path} is missing: the repository ships it under tests/data/real")
    return path


def real_dir(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_dir():
        pytest.fail(f"real capture folder {path} is missing: the repository ships it under tests/data/real")
    return path

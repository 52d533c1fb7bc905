"""Shared helpers for the driver tests: the real captures in ``../shared/testdata/real``."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "testdata" / "real"

#: hypothesis settings for the decoder properties (the folder must stay fast on 2 cores)
PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def real_file(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_file():
        pytest.fail(f"real capture {path} is missing: the tests need shared/testdata/real beside the project")
    return path


def real_dir(*parts: str) -> Path:
    path = REAL.joinpath(*parts)
    if not path.is_dir():
        pytest.fail(f"real capture folder {path} is missing: the tests need shared/testdata/real beside the project")
    return path

"""Fixtures shared across test folders (kept small: each area keeps its own helpers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_BUNDLE = PROJECT_ROOT / "examples" / "montreal-mini"


@pytest.fixture(scope="session")
def example_bundle() -> Path:
    """The small example bundle shipped in examples/ (made by examples/make_example_bundle.py)."""
    if not (EXAMPLE_BUNDLE / "site.yaml").is_file():
        pytest.fail(
            f"example bundle missing: {EXAMPLE_BUNDLE}; run "
            f"'.venv/bin/python examples/make_example_bundle.py'"
        )
    return EXAMPLE_BUNDLE


@pytest.fixture
def wave_trajectory():
    """Factory: a trajectory with swell (roll, pitch, yaw, heave) at ``rate_hz``, heading about
    ``heading_deg``, 2 m/s, starting at GPS second 1.313e9 (2021-08-17)."""
    from calib.core import frames
    from calib.core.trajectory import Trajectory

    def make(duration_s=4.0, rate_hz=200.0, heading_deg=30.0, sigmas=False, t0=1.313e9):
        t = t0 + np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
        s = t - t0
        rpy = np.stack(
            [
                np.radians(3.0) * np.sin(2 * np.pi * s / 6.0),
                np.radians(1.2) * np.sin(2 * np.pi * s / 4.3 + 0.5),
                frames.wrap_2pi(np.radians(heading_deg + 0.6 * np.sin(2 * np.pi * s / 9.0))),
            ],
            axis=1,
        )
        h = np.radians(heading_deg)
        p = np.stack([2 * np.cos(h) * s, 2 * np.sin(h) * s, 0.2 * np.sin(2 * np.pi * s / 5.5)], axis=1)
        kw = {}
        if sigmas:
            kw = dict(
                sigma_p_m=np.tile([0.02, 0.02, 0.03], (t.size, 1)) * (1 + 0.1 * s[:, None]),
                sigma_rpy_rad=np.radians(np.tile([0.01, 0.01, 0.02], (t.size, 1))),
            )
        return Trajectory(t, p, rpy, frames.LocalFrame(45.5, -73.55, -30.0), name="waves", **kw)

    return make

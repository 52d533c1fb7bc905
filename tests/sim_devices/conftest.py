"""Simulations shared by the emulator tests (each takes a fraction of a second)."""

from __future__ import annotations

import pytest

from calib.sim.simulate import simulate
from tests.sim_devices.harness import SHORT_PASSES


@pytest.fixture(scope="session")
def short_sim():
    """Montreal with 10 s lines 2 s apart and no scan-angle noise (pass 1 captures 2.8–7.2 s,
    its line ends at 10 s, pass 2 starts at 12 s)."""
    return simulate("montreal", 0, overrides=SHORT_PASSES)

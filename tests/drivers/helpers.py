"""Shared helpers for the driver tests: the real captures in ``tests/data/real`` (see its README),
and the fake host clock of the simulated devices in place of the real one."""

from __future__ import annotations

import contextlib
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


@contextlib.contextmanager
def fake_host_clock(path: Path, steps: list[tuple[int, int]]):
    """``drivers.timing`` reads realtime − monotonic through a :class:`~drivers.timing.FakeHostClock`
    with these ``(host monotonic ns, step ns)`` steps meanwhile; the real clock again after (and
    the step counter's offset re-read, so a later reader sees no step)."""
    from drivers import timing

    path.write_text("# host_monotonic_ns step_ns\n" + "".join(f"{t} {s}\n" for t, s in steps))
    saved = timing.FAKE_HOST_CLOCK
    timing.realtime_minus_monotonic_ns()
    timing.FAKE_HOST_CLOCK = timing.FakeHostClock(str(path), poll_ns=0)
    try:
        yield timing.FAKE_HOST_CLOCK
    finally:
        timing.FAKE_HOST_CLOCK = saved
        timing.realtime_minus_monotonic_ns()

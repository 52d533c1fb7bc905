"""Every command that writes a directory holds its writer lock: a second writer into the same
directory, --force or not, is refused in one line naming the holder (calib/io/dirlock.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.calib.io.test_dirlock import hold, release

ROOT = Path(__file__).resolve().parents[2]


def mls(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cli.app", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )


@pytest.mark.parametrize(
    ("args", "status"),
    [
        (("sim", "dataset", "--scenario", "montreal", "--force", "--out"), 2),
        (("calib", "georef", "examples/montreal-mini", "--force", "--out"), 1),
        (("watch", "examples/montreal-mini", "--force", "--out"), 1),
        (("design", "--scenario", "montreal", "--force", "--out"), 2),
        (("calib", "run", "examples/montreal-mini", "--force", "--out"), 2),
        (("georef", "examples/montreal-mini", "--force", "--out"), 1),
    ],
    ids=lambda v: " ".join(v[:2]) if isinstance(v, tuple) else str(v),
)
def test_a_second_writer_is_refused_in_one_line(tmp_path, args, status):
    out = tmp_path / "out"
    out.mkdir()
    other = hold(out)
    try:
        r = mls(*args, out)
    finally:
        release(other)
    text = (r.stdout + r.stderr).strip()
    assert r.returncode == status, text
    assert "Traceback" not in text and f"another writer holds it: pid {other.pid}" in text, text
    assert "(mls design --out x), started 20" in text
    assert sorted(p.name for p in out.iterdir()) == [".mls-lock"]  # nothing written

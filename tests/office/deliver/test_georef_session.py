"""``mls georef`` on a recorded session (written by ``mls sim session``: the daemon's format, two
closed segments): the same points, at the same coordinates, as ``mls export`` + georeferencing the
bundle; the returns outside the lines; an SBET trajectory; a segment torn by a crash."""

from __future__ import annotations

import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
from typer.testing import CliRunner

from cli.app import app
from office.deliver.engine import run_georef
from office.deliver.options import GeorefOptions
from office.jobs.export import ExportOptions, export_session

ARGS = ["--minutes", str(1 / 3), "--rate-scale", "0.02", "--rotate-s", "10"]
SETS = ["--set", "site.pass_length_m=16", "--set", "motion.pass_gap_s=2"]


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("georef-session")
    res = CliRunner().invoke(app, ["sim", "session", "--out", str(out), *ARGS, *SETS], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    (path,) = [p for p in out.iterdir() if p.is_dir()]
    return path


@pytest.fixture(scope="module")
def bundle(session, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("georef-session-bundle") / "bundle"
    export_session(session, out, ExportOptions(sbet_path=out.parent / "traj.sbet"))
    return out


def xyz(path: Path) -> tuple[np.ndarray, np.ndarray]:
    las = laspy.read(path)
    return np.stack([las.x, las.y, las.z], axis=1), np.asarray(las.gps_time)


def test_a_session_gives_what_its_exported_bundle_gives(session, bundle, tmp_path):
    s = run_georef(session, tmp_path / "s", GeorefOptions(chunk_s=3.0))
    b = run_georef(bundle, tmp_path / "b", GeorefOptions(chunk_s=3.0))
    names = sorted(p.name for p in (tmp_path / "s").glob("*.laz"))
    assert names == sorted(p.name for p in (tmp_path / "b").glob("*.laz")) == ["line-1.laz", "line-2.laz"]
    for name in names:
        ps, ts = xyz(tmp_path / "s" / name)
        pb, tb = xyz(tmp_path / "b" / name)
        assert ps.shape == pb.shape
        assert ps.shape[0] > 10_000
        assert np.abs(ts - tb).max() < 2e-6, np.abs(ts - tb).max()  # the same returns (points.csv: µs)
        # the bundle's CSV holds ranges to 0.1 mm and angles to 1e-6°: the same points within that
        assert np.abs(ps - pb).max() < 2e-3
    assert s.counters["datagrams"] > 0
    assert s.counters["bad_datagrams"] == 0
    assert s.counters["outside_lines"] > 0
    assert s.n_points == b.n_points
    las = laspy.read(tmp_path / "s" / "line-1.laz")
    assert np.all(np.asarray(las["sigma_h_m"]) > 0)
    assert np.all(las["pass_id"] == 1)


def test_transits_and_an_sbet_trajectory(session, bundle, tmp_path):
    lines = run_georef(session, tmp_path / "l", GeorefOptions())
    every = run_georef(session, tmp_path / "t", GeorefOptions(keep_transits=True))
    assert (tmp_path / "t" / "transit.laz").exists()
    assert every.n_points == lines.n_points + lines.counters["outside_lines"]
    sbet = run_georef(
        session,
        tmp_path / "sb",
        GeorefOptions(),
        sbet=bundle.parent / "traj.sbet",
        smrmsg=bundle.parent / "traj.smrmsg",
    )
    assert sbet.provenance["trajectory"].endswith("traj.sbet")
    a, _ = xyz(tmp_path / "l" / "line-1.laz")
    c, _ = xyz(tmp_path / "sb" / "line-1.laz")
    assert a.shape == c.shape
    assert np.abs(a - c).max() < 0.01


def test_a_torn_segment_is_read_up_to_its_tear_with_a_warning(session, tmp_path):
    torn = tmp_path / session.name
    shutil.copytree(session, torn)
    last = sorted(torn.glob("seg-*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[: last.stat().st_size // 2])  # a power cut mid-write
    whole = run_georef(session, tmp_path / "w", GeorefOptions(keep_transits=True))
    res = run_georef(torn, tmp_path / "o", GeorefOptions(keep_transits=True))
    assert 0 < res.n_points < whole.n_points
    assert any(last.name in w for w in res.warnings)
    assert "seg-000002.mcap" in (tmp_path / "o" / "summary.md").read_text()

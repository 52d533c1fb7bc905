"""``mls georef`` on a calibration bundle, in-process: what the tiles hold, the filters, the tiling,
the splitting of large tiles, resume after a kill, and the refusals."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from typer.testing import CliRunner

from calib.core import frames
from calib.core.georef import georeference
from calib.io.bundle import read_bundle
from calib.io.lastile import read_provenance
from calib.io.laz import output_crs
from cli.app import app
from office.deliver.engine import run_georef
from office.deliver.executors import InProcess
from office.deliver.options import Filters, GeorefError, GeorefOptions

runner = CliRunner()


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    from calib.sim.simulate import simulate

    out = tmp_path_factory.mktemp("georef") / "bundle"
    simulate("montreal", 3, overrides=["scanner.point_rate_scale=0.05"]).write(out)
    return out


def read_tiles(out: Path) -> dict[str, laspy.LasData]:
    return {p.stem: laspy.read(p) for p in sorted(out.glob("*.laz"))}


def test_line_tiles_hold_every_return_where_georeference_puts_it(bundle, tmp_path):
    res = run_georef(bundle, tmp_path / "out", GeorefOptions(chunk_s=2.0))
    b = read_bundle(bundle)
    pts = b.points
    tiles = read_tiles(tmp_path / "out")
    assert sorted(tiles) == [f"line-{p}" for p in sorted(pts.pass_ids())]
    crs = output_crs("utm", b.frame)
    for pid in pts.pass_ids():
        las = tiles[f"line-{pid}"]
        sel = (pts.pass_id == pid) & (pts.range_m >= 1.0)
        t = pts.t_gps_s[sel]
        order = np.argsort(t, kind="stable")
        want = crs.from_lgf(
            georeference(
                t[order], pts.range_m[sel][order], pts.scan_angle_rad[sel][order], b.trajectory, b.site.mount
            )
        )
        assert len(las.points) == sel.sum()
        got = np.stack([las.x, las.y, las.z], axis=1)
        assert np.abs(got - want).max() < 1.5e-4  # LAS resolution 0.1 mm
        assert np.allclose(frames.las_to_gps_seconds(las.gps_time), t[order], atol=1e-6)
        assert np.all(las["pass_id"] == pid)
        assert np.all(las.point_source_id == pid)
        assert las.header.point_format.id == 6
        assert str(las.header.version) == "1.4"
        sh, sv = np.asarray(las["sigma_h_m"]), np.asarray(las["sigma_v_m"])
        assert np.all(sh > 0.005)
        assert np.all(sv > 0.005)
        assert np.all(sh < 1)
        assert np.all(sv < 1)
    prov = read_provenance(tmp_path / "out" / "line-1.laz")
    assert prov["calibration"] is None
    assert prov["mount_id"]
    assert prov["software"].startswith("marine-mls")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["n_points"] == res.n_points == sum(len(t.points) for t in tiles.values())
    assert not (tmp_path / "out" / ".georef" / "parts").exists()  # parts gone after success


def test_a_calibration_sets_the_boresight_and_its_covariance_widens_sigma(bundle, tmp_path):
    from calib.boresight.result import write_result

    doc = {
        "boresight_deg": {"roll": 0.2, "pitch": 1.2, "yaw": 0.15},
        "sigma_deg": {"roll": 0.01, "pitch": 0.01, "yaw": 0.05},
        "sigma_scaled_deg": {"roll": 0.01, "pitch": 0.01, "yaw": 0.05},
        "sigma_realistic_deg": {"roll": 0.02, "pitch": 0.02, "yaw": 0.05},
        "correlation": [[1, 0.3, 0], [0.3, 1, 0], [0, 0, 1]],
        "sigma0_squared": 1.0,
        "n_points": 100,
        "software_version": "marine-mls test",
        "extras": {},
    }
    write_result(tmp_path / "result.json", doc)
    base = run_georef(bundle, tmp_path / "a", GeorefOptions())
    cal = run_georef(bundle, tmp_path / "b", GeorefOptions(), str(tmp_path / "result.json"))
    prov = read_provenance(tmp_path / "b" / "line-1.laz")
    assert prov["boresight_deg"] == [0.2, 1.2, 0.15]
    assert len(prov["result_fingerprint"]) == 64
    assert prov["boresight_sigma_deg"] == pytest.approx([0.02, 0.02, 0.05])
    a, b = laspy.read(tmp_path / "a" / "line-1.laz"), laspy.read(tmp_path / "b" / "line-1.laz")
    assert np.all(np.asarray(b["sigma_h_m"]) >= np.asarray(a["sigma_h_m"]) - 1e-7)
    assert np.median(np.asarray(b["sigma_h_m"]) - np.asarray(a["sigma_h_m"])) > 1e-4
    assert np.abs(np.asarray(b.x) - np.asarray(a.x)).max() > 1e-3  # another boresight moved them
    assert base.n_points == cal.n_points


def test_filters_leave_out_exactly_what_they_name(bundle, tmp_path):
    b = read_bundle(bundle)
    pts = b.points
    t0, t1 = float(pts.t_gps_s.min()), float(pts.t_gps_s.max())
    f = Filters(
        range_m=(12.0, 30.0),
        scan_angle_deg=(20.0, 200.0),
        intensity_min=5,
        time_gps_s=(t0 + 5.0, t1 - 5.0),
    )
    res = run_georef(bundle, tmp_path / "out", GeorefOptions(filters=f))
    from calib.io.bundle import intensity_scale

    inten = np.round(pts.intensity * intensity_scale(pts.intensity, b.points_path).factor)
    ang = np.degrees(pts.scan_angle_rad)
    t_ns = np.round(pts.t_gps_s * 1e9)
    keep = (pts.range_m >= 12) & (pts.range_m <= 30) & (ang >= 20) & (ang <= 200) & (inten >= 5)
    keep &= (t_ns >= round((t0 + 5) * 1e9)) & (t_ns <= round((t1 - 5) * 1e9))
    assert res.n_points == keep.sum() > 0
    assert res.counters["returns"] == pts.t_gps_s.size
    dropped = sum(v for k, v in res.counters.items() if k.startswith(("outside", "below")))
    assert dropped == pts.t_gps_s.size - keep.sum()
    assert "below_intensity_floor" in res.counters
    assert "outside_scan_angle_window" in res.counters


def test_the_vessel_box_leaves_out_the_returns_inside_it(bundle, tmp_path):
    b = read_bundle(bundle)
    v_b = frames.scanner_vector(b.points.range_m, b.points.scan_angle_rad) @ b.site.mount.r_s_b.T
    v_b += b.site.mount.lever_arm_m
    box = (-50.0, 50.0, -50.0, float(np.median(v_b[:, 1])), -50.0, 50.0)  # half of the returns
    res = run_georef(bundle, tmp_path / "out", GeorefOptions(filters=Filters(vessel_box_m=box)))
    inside = (v_b[:, 1] <= box[3]) & (b.points.range_m >= 1.0)
    assert res.counters["vessel_itself"] == inside.sum() > 0
    assert res.n_points == (~inside & (b.points.range_m >= 1.0)).sum()


def test_square_tiles_put_each_point_in_its_square_and_big_tiles_are_split(bundle, tmp_path):
    run_georef(bundle, tmp_path / "sq", GeorefOptions(tiling="square", tile_m=2.0, chunk_s=1.0))
    tiles = read_tiles(tmp_path / "sq")
    assert len(tiles) >= 3
    for name, las in tiles.items():
        e, n = (float(v) for v in name.split("-")[1:3])
        assert np.all((las.x >= e) & (las.x < e + 2.0) & (las.y >= n) & (las.y < n + 2.0)), name
    whole = run_georef(bundle, tmp_path / "line", GeorefOptions(chunk_s=1.0))
    small = run_georef(bundle, tmp_path / "split", GeorefOptions(chunk_s=1.0, max_tile_points=1000))
    assert small.n_points == whole.n_points
    names = [f["name"] for f in small.files]
    assert any(n.endswith("-p02") for n in names)
    for f in small.files:  # a file exceeds the limit only when one chunk's part does
        assert f["n_points"] <= 1000 or "-p" not in f["name"] or f["n_points"] < 2 * 1000
    split = read_tiles(tmp_path / "split")
    t = np.concatenate([split[n].gps_time for n in sorted(split) if n.startswith("line-1-p")])
    assert np.all(np.diff(t) >= 0)  # the pieces of a line follow each other in time
    assert np.array_equal(np.sort(t), np.sort(read_tiles(tmp_path / "line")["line-1"].gps_time))


class _Killed(Exception):
    pass


class _DiesAfter(InProcess):
    """An executor whose process 'dies' when the ``n``-th task of the stage ``stage_fn`` starts."""

    def __init__(self, n: int, stage_fn: str):
        super().__init__()
        self.n, self.stage_fn, self.seen = n, stage_fn, 0

    def results(self):
        while self._queue:
            fn, item = self._queue.popleft()
            if fn.__name__ == self.stage_fn:
                if self.seen == self.n:
                    raise _Killed
                self.seen += 1
            yield fn(item)


@pytest.mark.parametrize("stage", ["process_chunk", "write_file"])
def test_a_killed_job_resumes_and_writes_the_same_bytes(bundle, tmp_path, stage):
    opts = GeorefOptions(chunk_s=1.0)
    run_georef(bundle, tmp_path / "ref", opts)
    with pytest.raises(_Killed):
        run_georef(bundle, tmp_path / "out", opts, executor=_DiesAfter(3, stage))
    done = sorted(p.name for p in (tmp_path / "out").glob("*.laz"))
    assert not list((tmp_path / "out").glob("*.partial"))
    res = run_georef(bundle, tmp_path / "out", opts, resume=True)
    if stage == "process_chunk":
        assert res.chunks_run == res.chunks - 3
    else:
        assert res.chunks_run == 0
        assert res.files_run == len(res.files) - len(done)
        assert len(done) == 3
    ref = {p.name: p.read_bytes() for p in (tmp_path / "ref").glob("*.laz")}
    got = {p.name: p.read_bytes() for p in (tmp_path / "out").glob("*.laz")}
    assert got == ref


def test_a_tile_interrupted_while_written_leaves_no_file(bundle, tmp_path, monkeypatch):
    from calib.io import tileparts

    real = tileparts._write_points
    calls = {"n": 0}

    def unplugged(f, parts):
        calls["n"] += 1
        if calls["n"] == 3:  # the third file: its first part written, then the disk is gone
            real(f, parts[:1])
            raise OSError("disk unplugged")
        real(f, parts)

    monkeypatch.setattr(tileparts, "_write_points", unplugged)
    with pytest.raises(OSError, match="disk unplugged"):
        run_georef(bundle, tmp_path / "out", GeorefOptions(chunk_s=1.0))
    monkeypatch.undo()
    assert calls["n"] == 3
    assert not list((tmp_path / "out").glob("*.partial"))
    names = {p.stem for p in (tmp_path / "out").glob("*.laz")}
    res = run_georef(bundle, tmp_path / "out", GeorefOptions(chunk_s=1.0), resume=True)
    assert res.files_run == len(res.files) - len(names)


def test_refusals_name_the_problem(bundle, tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.laz").write_bytes(b"")
    with pytest.raises(GeorefError, match="not empty.*--force"):
        run_georef(bundle, tmp_path / "full", GeorefOptions())
    with pytest.raises(GeorefError, match="no job to resume"):
        run_georef(bundle, tmp_path / "full", GeorefOptions(), resume=True)
    run_georef(bundle, tmp_path / "out", GeorefOptions())
    with pytest.raises(GeorefError, match="other inputs or options"):
        run_georef(bundle, tmp_path / "out", GeorefOptions(crs="lgf"), resume=True)
    with pytest.raises(GeorefError, match="--tile-m"):
        GeorefOptions(tiling="square")
    with pytest.raises(GeorefError, match="--range-m 5 2"):
        Filters(range_m=(5, 2))
    with pytest.raises(GeorefError, match="--vessel-box-m"):
        Filters(vessel_box_m=(1, 0, 0, 1, 0, 1))
    with pytest.raises(GeorefError, match="neither a session"):
        run_georef(tmp_path, tmp_path / "o2", GeorefOptions())


def test_the_command_line(bundle, tmp_path):
    r = runner.invoke(
        app,
        ["georef", str(bundle), "--out", str(tmp_path / "o"), "--tile-m", "5", "--range-m", "2", "60"],
        env={"COLUMNS": "200"},
    )
    assert r.exit_code == 0, r.output
    assert "points in" in r.output
    assert "summary.md" in r.output
    assert (tmp_path / "o" / "summary.md").read_text().startswith("# Survey deliverable")
    r = runner.invoke(app, ["georef", str(bundle), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1
    assert "--force" in r.output
    r = runner.invoke(app, ["georef", str(bundle), "--out", str(tmp_path / "o"), "--resume", "--force"])
    assert r.exit_code == 1
    assert "choose one" in r.output

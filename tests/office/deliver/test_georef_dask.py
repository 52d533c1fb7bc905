"""``mls georef`` on a real ``dask.distributed`` LocalCluster of two worker processes: a worker
killed (SIGKILL) in the middle of the job, the job still finishes and every tile is complete and
byte-identical to an in-process run."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from office.deliver.chunkjob import process_chunk
from office.deliver.engine import run_georef
from office.deliver.executors import DaskExecutor
from office.deliver.options import GeorefOptions
from tests.office.deliver.slowtasks import slow_process_chunk

pytestmark = [pytest.mark.integration]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    from calib.sim.simulate import simulate

    out = tmp_path_factory.mktemp("georef-dask") / "bundle"
    simulate("montreal", 5, overrides=["scanner.point_rate_scale=0.05"]).write(out)
    return out


class KillsAWorker(DaskExecutor):
    """Chunks slowed to 0.3 s each; when the first one is back, the other worker (busy with a
    chunk of its own) is killed."""

    killed: int | None = None
    pids: set[int] = set()

    def submit(self, fn, item):
        super().submit(slow_process_chunk if fn is process_chunk else fn, item)

    def results(self):
        for res in super().results():
            self.pids.add(res.pid)
            if self.killed is None:
                victim = next(p for p in self.worker_pids() if p != res.pid)
                os.kill(victim, signal.SIGKILL)
                self.killed = victim
            yield res


def test_a_worker_killed_mid_job_costs_nothing(bundle, tmp_path):
    opts = GeorefOptions(chunk_s=0.5, tiling="square", tile_m=2.0)
    ref = run_georef(bundle, tmp_path / "ref", opts)
    ex = KillsAWorker(workers=2)
    try:
        assert len(ex.worker_pids()) == 2
        res = run_georef(bundle, tmp_path / "out", opts, executor=ex)
        ex.client.wait_for_workers(2, timeout=60)  # the job may end before the nanny's restart
        after = ex.worker_pids()
    finally:
        ex.close()
    assert ex.killed is not None
    assert ex.killed not in after
    assert len(after) == 2
    assert res.chunks_run == res.chunks >= 12
    assert res.n_points == ref.n_points
    want = {p.name: p.read_bytes() for p in (tmp_path / "ref").glob("*.laz")}
    got = {p.name: p.read_bytes() for p in (tmp_path / "out").glob("*.laz")}
    assert got == want
    assert len(got) >= 3
    assert not list((tmp_path / "out").rglob("*.tmp"))
    assert not list((tmp_path / "out").glob("*.partial"))


def test_mls_georef_on_a_running_cluster_named_by_its_address(bundle, tmp_path):
    from distributed import LocalCluster
    from typer.testing import CliRunner

    from cli.app import app

    opts = GeorefOptions(chunk_s=1.0)
    run_georef(bundle, tmp_path / "ref", opts)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        args = ["georef", str(bundle), "--out", str(tmp_path / "out"), "--chunk-s", "1"]
        r = CliRunner().invoke(app, [*args, "--scheduler", cluster.scheduler_address], env={"COLUMNS": "250"})
    assert r.exit_code == 0, r.output
    assert f"dask {cluster.scheduler_address}" in r.output
    want = {p.name: p.read_bytes() for p in (tmp_path / "ref").glob("*.laz")}
    assert {p.name: p.read_bytes() for p in (tmp_path / "out").glob("*.laz")} == want
    assert want


class CountsTasks(DaskExecutor):
    """The names of the functions of the tasks submitted."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.submitted: list[str] = []

    def submit(self, fn, item):
        self.submitted.append(item[0].__name__ if fn.__name__ == "_numbered" else fn.__name__)
        super().submit(fn, item)


def test_a_session_s_navigation_is_read_on_the_workers_and_the_tiles_do_not_change(tmp_path):
    """On two workers the plan shares the reading of the navigation out to them (the plan is the
    job's serial part); the tiles are byte for byte those of an in-process run."""
    from typer.testing import CliRunner

    from cli.app import app

    args = ["--minutes", str(1 / 6), "--rate-scale", "0.01", "--rotate-s", "10"]
    args += ["--set", "site.pass_length_m=10", "--set", "motion.pass_gap_s=2"]
    r = CliRunner().invoke(
        app, ["sim", "session", "--out", str(tmp_path / "s"), *args], env={"COLUMNS": "250"}
    )
    assert r.exit_code == 0, r.output
    (session,) = (tmp_path / "s").iterdir()
    opts = GeorefOptions(chunk_s=2.0)
    ref = run_georef(session, tmp_path / "ref", opts)
    ex = CountsTasks(workers=2)
    try:
        res = run_georef(session, tmp_path / "out", opts, executor=ex)
    finally:
        ex.close()
    assert ex.submitted.count("nav_piece") >= 2 * len(list(session.glob("seg-*.mcap")))
    assert ex.submitted.index("process_chunk") > max(
        i for i, n in enumerate(ex.submitted) if n == "nav_piece"
    )
    assert res.n_points == ref.n_points > 0
    want = {p.name: p.read_bytes() for p in (tmp_path / "ref").glob("*.laz")}
    assert {p.name: p.read_bytes() for p in (tmp_path / "out").glob("*.laz")} == want

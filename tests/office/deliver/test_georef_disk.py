"""``mls georef`` and the disk: one writer per ``--out`` (a second is refused, naming the
first), the space a job needs checked up front, and a disk that fills up mid-job: one line, no
temporary file left, and ``--resume`` then finishes with the bytes of an uninterrupted run."""

from __future__ import annotations

import builtins
import errno
import json
import os
import select
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import calib.io.tileparts as tileparts
import office.deliver.chunkjob as chunkjob
import office.deliver.engine as engine
import office.deliver.space as space
import office.deliver.tiles as tiles
from calib.io.dirlock import LOCK_NAME
from calib.io.lastile import read_provenance
from cli.app import app
from office.deliver.engine import run_georef
from office.deliver.options import GeorefError, GeorefOptions

ROOT = Path(__file__).resolve().parents[3]
OPTS = GeorefOptions(chunk_s=1.0)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    from calib.sim.simulate import simulate

    out = tmp_path_factory.mktemp("georef-disk") / "bundle"
    simulate("montreal", 3, overrides=["scanner.point_rate_scale=0.05"]).write(out)
    return out


@pytest.fixture(scope="module")
def reference(bundle, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("georef-disk-ref") / "out"
    run_georef(bundle, out, OPTS)
    return {p.name: p.read_bytes() for p in out.glob("*.laz")}


def tiles_of(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in out.glob("*.laz")}


def leftovers(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.name.endswith((".tmp", ".partial")))


def wait_readable(fd: int, timeout_s: float, what: str, proc: subprocess.Popen) -> None:
    """Block until the pipe ``fd`` has a byte (the writer's signal), at most ``timeout_s``."""
    if not select.select([fd], [], [], timeout_s)[0]:
        assert proc.stderr is not None  # the writer is started with its stderr piped
        state = "running" if proc.poll() is None else f"ended ({proc.returncode}): {proc.stderr.read()}"
        raise AssertionError(f"no signal within {timeout_s} s for {what}; the writer is {state}")


def mls(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cli.app", *args], capture_output=True, text=True, cwd=ROOT, timeout=120
    )


def test_a_second_writer_into_the_same_out_is_refused_naming_the_first(bundle, reference, tmp_path):
    out = tmp_path / "out"
    started_r, started_w = os.pipe()
    go_r, go_w = os.pipe()
    first = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tests.office.deliver.heldwriter",
            str(bundle),
            str(out),
            str(started_w),
            str(go_r),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        pass_fds=(started_w, go_r),
    )
    try:
        wait_readable(started_r, 60, "the first writer planned", first)
        for mode in ("--force", "--resume"):
            second = mls("georef", str(bundle), "--out", str(out), "--chunk-s", "1", mode)
            assert second.returncode == 1, (mode, second.stdout, second.stderr)
            lines = second.stderr.strip().splitlines()
            assert len(lines) == 1, second.stderr
            assert "Traceback" not in second.stderr, second.stderr
            assert f"pid {first.pid} on {socket.gethostname()}" in lines[0]
            assert "heldwriter" in lines[0]
            assert "started 20" in lines[0]
            assert str(out) in lines[0]
        os.write(go_w, b"g")
        assert first.stderr is not None  # started with its stderr piped
        assert first.wait(120) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        first.stdout.close()  # type: ignore[union-attr]
        first.stderr.close()  # type: ignore[union-attr]
        for fd in (started_r, started_w, go_r, go_w):
            os.close(fd)
    assert tiles_of(out) == reference  # the first writer's tiles, with its provenance, untouched
    assert all(read_provenance(p)["crs"] for p in out.glob("*.laz"))
    assert not (out / LOCK_NAME).exists()  # released: the deliverable holds no lock file
    again = mls("georef", str(bundle), "--out", str(out), "--chunk-s", "1", "--force")
    assert again.returncode == 0, again.stderr
    assert tiles_of(out) == reference


def test_a_lock_left_by_a_dead_writer_is_no_obstacle(bundle, reference, tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    out = tmp_path / "out"
    out.mkdir()
    record = {"pid": dead.pid, "host": socket.gethostname(), "command": "mls georef", "started_utc": "x"}
    (out / LOCK_NAME).write_text(json.dumps(record))
    run_georef(bundle, out, OPTS)  # the stale lock is not content either: no --force needed
    assert tiles_of(out) == reference
    assert not (out / LOCK_NAME).exists()


def test_a_symlink_at_the_lock_path_is_refused_and_not_followed(bundle, tmp_path):
    out, target = tmp_path / "out", tmp_path / "precious"
    out.mkdir()
    target.write_text("keep me")
    (out / LOCK_NAME).symlink_to(target)
    with pytest.raises(GeorefError, match="symbolic link"):
        run_georef(bundle, out, OPTS, force=True)
    assert target.read_text() == "keep me"


def test_a_job_the_disk_cannot_hold_is_refused_up_front(bundle, tmp_path, monkeypatch):
    real = space.shutil.disk_usage
    monkeypatch.setattr(space.shutil, "disk_usage", lambda p: real(p)._replace(free=200_000))
    with pytest.raises(GeorefError) as e:
        run_georef(bundle, tmp_path / "out", OPTS)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(tmp_path / "out") in msg
    assert "not enough free space" in msg
    assert "MB free" in msg
    assert "needs about" in msg
    assert not (tmp_path / "out").exists()  # made for the job, left as it was: nothing


def test_the_estimate_covers_what_a_job_takes(bundle, tmp_path, monkeypatch):
    from office.deliver.sources import open_source

    peak = {"bytes": 0}
    real = chunkjob.write_atomic

    def measuring(path, data):
        real(path, data)
        size = sum(p.stat().st_size for p in (tmp_path / "out").rglob("*") if p.is_file())
        peak["bytes"] = max(peak["bytes"], size)

    monkeypatch.setattr(chunkjob, "write_atomic", measuring)
    monkeypatch.setattr(tiles, "write_atomic", measuring)
    run_georef(bundle, tmp_path / "out", OPTS)
    need = space.space_needed(space.source_returns(open_source(bundle, 1.0)), True)
    assert peak["bytes"] < need  # (a small job's need is mostly the fixed allowance)
    assert need - space.FIXED_BYTES < 3 * peak["bytes"]


class FullDisk:
    """``open`` whose files fail with ENOSPC once ``budget`` bytes are written (the failing write
    gets half of its bytes through, as a real one does)."""

    def __init__(self, budget: int):
        self.left = budget

    def open(self, path, mode="r", *args, **kwargs):
        f = builtins.open(path, mode, *args, **kwargs)
        return f if "w" not in mode else _Filling(f, self, str(path))


class _Filling:
    def __init__(self, f, disk: FullDisk, path: str):
        self.f, self.disk, self.path = f, disk, path

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.f.close()

    def write(self, data) -> int:
        n = len(data)
        if n > self.disk.left:
            self.f.write(bytes(data[: n // 2]))
            self.f.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self.path)
        self.disk.left -= n
        return self.f.write(data)

    def flush(self) -> None:
        self.f.flush()

    def fileno(self) -> int:
        return self.f.fileno()


def test_a_disk_full_mid_job_is_one_line_leaves_no_temporary_and_resumes(
    bundle, reference, tmp_path, monkeypatch
):
    out = tmp_path / "out"
    monkeypatch.setattr(tileparts, "open", FullDisk(60_000).open, raising=False)
    with pytest.raises(GeorefError) as e:
        run_georef(bundle, out, OPTS)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(out) in msg
    assert "no space left" in msg
    assert "MB" in msg
    assert "--resume" in msg
    assert leftovers(out) == []
    monkeypatch.undo()
    run_georef(bundle, out, OPTS, resume=True)
    assert tiles_of(out) == reference
    assert leftovers(out) == []
    assert not (out / ".georef" / "parts").exists()


def test_a_disk_full_while_a_tile_is_written_leaves_no_partial_file(bundle, reference, tmp_path, monkeypatch):
    out = tmp_path / "out"
    real = tileparts.write_tile
    calls = {"n": 0}

    def fills_up(path, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:  # the LAZ writer fails, and so does closing it: the partial file stays
            Path(str(path) + ".partial").write_bytes(b"LASF")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(tileparts, "write_tile", fills_up)
    r = CliRunner().invoke(app, ["georef", str(bundle), "--out", str(out), "--chunk-s", "1"])
    assert r.exit_code == 1, r.output
    assert "no space left" in r.output, r.output
    assert isinstance(r.exception, SystemExit)  # MlsGroup's one line, no traceback
    assert leftovers(out) == []
    monkeypatch.undo()
    run_georef(bundle, out, OPTS, resume=True)
    assert tiles_of(out) == reference


def test_parts_lost_with_the_power_run_their_chunks_again(bundle, reference, tmp_path, monkeypatch):
    """The parts are not synced: a part the machine's power took (empty, or gone) is not taken
    for a whole one; its chunk runs again on --resume, and the tiles are those of a clean run."""
    out = tmp_path / "out"

    def power_lost(*args, **kwargs):
        raise OSError("power lost")

    monkeypatch.setattr(tileparts, "write_tile", power_lost)  # every chunk done, no tile yet
    with pytest.raises(OSError, match="power lost"):
        run_georef(bundle, out, OPTS)
    monkeypatch.undo()
    parts = sorted((out / ".georef" / "parts").rglob("*.part"))
    parts[0].write_bytes(b"")
    parts[-1].write_bytes(b"\0" * parts[-1].stat().st_size)
    lost = {int(parts[0].stem[1:]), int(parts[-1].stem[1:])}
    res = run_georef(bundle, out, OPTS, resume=True)
    assert res.chunks_run == len(lost)
    assert tiles_of(out) == reference
    assert leftovers(out) == []


@pytest.fixture
def small_disk(tmp_path):
    """A tmpfs of 192 KB (root only: skipped where mounting is not allowed)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=192k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def test_a_real_full_disk_is_refused_up_front_then_met_mid_job_and_resumed(
    bundle, reference, small_disk, monkeypatch
):
    out = small_disk / "out"
    with pytest.raises(GeorefError, match="not enough free space"):
        run_georef(bundle, out, OPTS)
    monkeypatch.setattr(engine, "check_space", lambda out, need: None)  # as if the estimate were wrong
    with pytest.raises(GeorefError) as e:
        run_georef(bundle, out, OPTS)
    assert "no space left on the device" in str(e.value)
    assert "\n" not in str(e.value)
    assert leftovers(out) == []
    subprocess.run(["mount", "-o", "remount,size=8m", str(small_disk)], check=True)
    monkeypatch.undo()
    run_georef(bundle, out, OPTS, resume=True)
    assert tiles_of(out) == reference
    assert leftovers(out) == []

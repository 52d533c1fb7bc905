"""One writer per output directory (calib/io/dirlock.py): the lock names its holder, a second
writer is refused even with --force, a dead writer's lock is no obstacle, a symlink is never
followed, and a finished writer leaves no lock file."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from calib.io.dirlock import LOCK_NAME, DirLock, OutputLocked
from calib.io.outputs import OutputError, check_output_dir, lock_output_dir

HOLD = (
    "import sys; from calib.io.dirlock import DirLock; "
    "lock = DirLock(sys.argv[1], 'mls design --out x'); lock.acquire(); print('held', flush=True); "
    "sys.stdin.read()"
)
ROOT = Path(__file__).resolve().parents[3]


def hold(directory: Path) -> subprocess.Popen:
    """Another process holding ``directory``'s lock until its stdin closes (it says when it holds it)."""
    p = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(directory)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert p.stdout is not None and p.stdout.readline() == "held\n"  # blocks until it holds it
    return p


def release(p: subprocess.Popen) -> int:
    """End a :func:`hold`: close its stdin, wait for it to exit (its status), close its pipes."""
    p.stdin.close()  # type: ignore[union-attr]
    try:
        return p.wait(30)
    finally:
        p.stdout.close()  # type: ignore[union-attr]


def test_a_second_writer_is_refused_naming_the_holder_even_forced(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    other = hold(out)
    try:
        for force in (False, True):
            with pytest.raises(OutputLocked) as e:
                lock_output_dir(out, "--out", force)
            msg = str(e.value)
            assert "\n" not in msg and msg.startswith(f"{out}: another writer holds it: pid {other.pid}")
            assert f"on {socket.gethostname()} (mls design --out x), started 20" in msg
        record = json.loads((out / LOCK_NAME).read_text())
        assert record["pid"] == other.pid and record["command"] == "mls design --out x"
    finally:
        assert release(other) == 0
    with lock_output_dir(out, "--out"):  # released with its holder; the lock is no content
        assert (out / LOCK_NAME).exists()
    assert not (out / LOCK_NAME).exists()


def test_a_killed_holder_leaves_a_lock_that_is_taken_over(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    other = hold(out)
    other.kill()
    release(other)
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == other.pid  # left behind
    check_output_dir(out, "--out")  # not content: no --force needed
    lock = lock_output_dir(out, "--out")
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == os.getpid()
    lock.release()
    assert list(out.iterdir()) == []


def test_a_taker_that_locked_a_released_file_takes_the_new_one(tmp_path):
    first = DirLock(tmp_path, "first")
    first.acquire()
    fd = os.open(first.path, os.O_RDWR)  # a second taker opened the file before it was released
    first.release()
    second = DirLock(tmp_path, "second")
    second.acquire()  # a new file: not the unlinked one
    st, own = os.stat(second.path), os.fstat(fd)
    assert (st.st_dev, st.st_ino) != (own.st_dev, own.st_ino)
    assert json.loads(second.path.read_text())["command"] == "second"
    os.close(fd)
    second.release()


def test_a_symlink_at_the_lock_path_is_refused_and_not_followed(tmp_path):
    target = tmp_path / "precious"
    target.write_text("keep me")
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).symlink_to(target)
    with pytest.raises(OutputLocked, match="is a symbolic link; remove it"):
        lock_output_dir(out, "--out", force=True)
    assert target.read_text() == "keep me"


def test_a_refused_directory_is_left_as_it_was(tmp_path):
    full = tmp_path / "full"
    full.mkdir()
    (full / "x.laz").write_bytes(b"")
    with pytest.raises(OutputError, match="not empty"):
        lock_output_dir(full, "--out")
    assert sorted(p.name for p in full.iterdir()) == ["x.laz"]  # no lock file left
    made = tmp_path / "new" / "out"
    lock_output_dir(made, "--out").release()  # made for a writer that wrote nothing: removed
    assert not made.exists()

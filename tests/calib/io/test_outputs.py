"""calib.io.outputs: output directories and files named on the command line are checked before
anything is written; data is never overwritten without --force."""

from __future__ import annotations

import pytest

from calib.core.errors import MlsError
from calib.io.outputs import OutputError, check_output_dir, check_output_file, make_output_dir


def test_output_directory_rules(tmp_path):
    assert issubclass(OutputError, MlsError)
    fresh = tmp_path / "a" / "b"
    assert check_output_dir(fresh, "--out") == fresh and not fresh.exists()  # creates nothing
    assert make_output_dir(fresh).is_dir()
    check_output_dir(fresh, "--out")  # empty: fine
    (fresh / "result.json").write_text("{}")
    with pytest.raises(
        OutputError,
        match=r"b: --out is not empty \(result\.json\); add --force to write into it anyway",
    ):
        check_output_dir(fresh, "--out")
    assert check_output_dir(fresh, "--out", force=True) == fresh
    for i in range(4):
        (fresh / f"pass-{i}.laz").write_bytes(b"")
    with pytest.raises(
        OutputError, match=r"--laz is not empty \(pass-0\.laz, pass-1\.laz, pass-2\.laz, … \(5 entries\)\)"
    ):
        check_output_dir(fresh, "--laz")
    afile = tmp_path / "afile"
    afile.write_text("x")
    for force in (False, True):
        with pytest.raises(OutputError, match=r"afile: --out names a directory, but this is a file"):
            check_output_dir(afile, "--out", force)
    with pytest.raises(OutputError, match=r"afile: --out names a directory, but this is a file"):
        make_output_dir(afile)
    with pytest.raises(OutputError, match=r"inside: --out: cannot create the directory \(Not a directory\)"):
        make_output_dir(afile / "inside")


def test_output_file_rules(tmp_path):
    p = tmp_path / "traj.sbet"
    assert check_output_file(p, "--sbet") == p
    p.write_bytes(b"old")
    with pytest.raises(OutputError, match=r"traj\.sbet: --sbet: the file exists; add --force to replace it"):
        check_output_file(p, "--sbet")
    assert check_output_file(p, "--sbet", force=True) == p
    with pytest.raises(OutputError, match=r": --sbet names a file, but this is a directory"):
        check_output_file(tmp_path, "--sbet", force=True)

"""Nothing silent: every malformed input of the corpus (tests/corpus/make_corpus.py, written
afresh into a temporary directory for each case) is refused by ``mls calib run``, ``mls calib
georef``, ``mls export`` or ``mls acquire --check`` with the exit status and the first line of
message that tests/corpus/cases.py records, and never with a traceback.

The cases run in-process through typer's CliRunner (the whole corpus takes seconds); the few
marked ``subprocess`` run once more through the console entry point, where rich writes to a
pipe 80 columns wide.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.app import app
from tests.corpus import make_corpus
from tests.corpus.cases import CASES, Case

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def _argv(case: Case, case_dir: Path) -> list[str]:
    return [a.replace("{case}", str(case_dir)) for a in case.argv]


def _check(case: Case, case_dir: Path, status: int, stdout: str, stderr: str) -> None:
    output = f"exit status {status}\n--- stdout\n{stdout}\n--- stderr\n{stderr}"
    assert "Traceback" not in stdout + stderr, output
    assert status == case.status, output
    lines = [line.rstrip() for line in stderr.splitlines() if line.strip()]
    assert lines, f"nothing on stderr\n{output}"
    if case.regex:
        pattern = case.first_line.replace("{case}", re.escape(str(case_dir)))
        assert re.fullmatch(pattern, lines[0]), f"{lines[0]!r}\ndoes not match\n{pattern!r}"
    else:
        assert lines[0] == case.first_line.replace("{case}", str(case_dir))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_a_malformed_input_is_refused_in_one_line(tmp_path, case):
    case_dir = make_corpus.build(case.defect, tmp_path)
    res = CliRunner().invoke(app, _argv(case, case_dir))
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception  # escaped the command: its traceback is the failure
    _check(case, case_dir, res.exit_code, res.stdout, res.stderr)


@pytest.mark.parametrize("case", [c for c in CASES if c.subprocess], ids=lambda c: c.id)
def test_the_console_entry_point_says_the_same(tmp_path, case):
    case_dir = make_corpus.build(case.defect, tmp_path)
    res = subprocess.run(
        [sys.executable, "-m", "cli.app", *_argv(case, case_dir)],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    _check(case, case_dir, res.returncode, res.stdout, res.stderr)


def test_every_defect_has_a_case_and_every_case_a_defect():
    defects = {c.defect for c in CASES}
    assert sorted(set(make_corpus.DEFECTS) - defects) == []
    assert sorted(defects - set(make_corpus.DEFECTS)) == []
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids))
    assert {c.command for c in CASES} == {"calib run", "calib georef", "export", "acquire --check"}


@pytest.mark.parametrize(
    ("make", "argv"),
    [
        (make_corpus.valid_bundle, ("calib", "georef", "{case}/bundle", "--out", "{case}/laz")),
        (make_corpus.valid_vessel, ("acquire", "--check", "--config", "{case}/vessel.yaml")),
        (make_corpus.valid_session, ("export", "{case}/session", "--bundle", "{case}/out")),
    ],
    ids=["bundle", "vessel", "session"],
)
def test_the_inputs_the_defects_start_from_are_valid(tmp_path, make, argv):
    """Each case's input differs from one of these by its one defect: the defect is why it fails."""
    make(tmp_path)
    res = CliRunner().invoke(app, [a.replace("{case}", str(tmp_path)) for a in argv])
    assert res.exit_code == 0, res.output


def test_the_generator_writes_the_corpus_by_hand(tmp_path, capsys):
    assert make_corpus.main([str(tmp_path), "points-nan", "vessel-bad-port"]) == 0
    assert capsys.readouterr().out.split() == [
        str(tmp_path / "points-nan"),
        str(tmp_path / "vessel-bad-port"),
    ]
    assert (tmp_path / "points-nan" / "bundle" / "points.csv").is_file()
    assert (tmp_path / "vessel-bad-port" / "vessel.yaml").is_file()
    with pytest.raises(SystemExit):  # the directories are taken now
        make_corpus.main([str(tmp_path), "points-nan"])

"""The corpus of malformed inputs ("Nothing silent"): one case per defect, each derived from a
valid input by one edit, so that each input fails for exactly one reason.

- bundles, from the example bundle ``examples/montreal-mini`` (``site.yaml``, ``points.csv``
  written out plain from its ``points.csv.gz``, ``trajectory.csv``): for ``mls calib run`` and
  ``mls calib georef``;
- vessel configs, from ``systemd/vessel.example.yaml``: for ``mls acquire --check``;
- recorded sessions, from the tiny session of ``tests/office/jobs/test_export.py``: for ``mls
  export``.

:data:`DEFECTS` maps a defect id to the function that writes its input into a directory of its
own; ``tests/corpus/cases.py`` says which command runs on it and what that command must answer,
``tests/corpus/test_corpus.py`` checks it. Nothing generated is committed: the test writes the
corpus into a temporary directory, and by hand

    .venv/bin/python -m tests.corpus.make_corpus /tmp/corpus [DEFECT ...]

writes it (or the named defects) under ``/tmp/corpus/<defect>/``, which ``mls`` can then be run
on (``bundle/``, ``vessel.yaml`` or ``session/`` in each).
"""

from __future__ import annotations

import argparse
import gzip
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_BUNDLE = PROJECT_ROOT / "examples" / "montreal-mini"
EXAMPLE_VESSEL = PROJECT_ROOT / "systemd" / "vessel.example.yaml"

#: defect id -> writer of its input into the (empty, existing) case directory
DEFECTS: dict[str, Callable[[Path], None]] = {}


def defect(name: str):
    def register(fn: Callable[[Path], None]) -> Callable[[Path], None]:
        assert name not in DEFECTS, name
        DEFECTS[name] = fn
        return fn

    return register


# -- valid starting points --------------------------------------------------------------------


def valid_bundle(case: Path) -> Path:
    """``case/bundle``: the example bundle with a plain ``points.csv`` (lines to edit) and
    without ``truth.json`` (never read by the commands)."""
    b = case / "bundle"
    b.mkdir()
    shutil.copy(EXAMPLE_BUNDLE / "site.yaml", b / "site.yaml")
    shutil.copy(EXAMPLE_BUNDLE / "trajectory.csv", b / "trajectory.csv")
    (b / "points.csv").write_bytes(gzip.decompress((EXAMPLE_BUNDLE / "points.csv.gz").read_bytes()))
    return b


def _edit_text(path: Path, old: str, new: str, count: int = 1) -> None:
    """Replace the first ``count`` occurrences of ``old`` (which must be there)."""
    text = path.read_text()
    if text.count(old) < count:  # the valid input changed: the defect must be derived anew
        raise ValueError(f"{path}: {old!r} not found {count} time(s)")
    path.write_text(text.replace(old, new, count))


def _edit_line(path: Path, line: int, edit: Callable[[list[str]], list[str]]) -> None:
    """Apply ``edit`` to the comma-separated fields of line ``line`` (1-based) of a CSV."""
    lines = path.read_text().split("\n")
    lines[line - 1] = ",".join(edit(lines[line - 1].split(",")))
    path.write_text("\n".join(lines))


def _set_field(index: int, value: str) -> Callable[[list[str]], list[str]]:
    def edit(fields: list[str]) -> list[str]:
        fields[index] = value
        return fields

    return edit


# -- site.yaml --------------------------------------------------------------------------------


@defect("site-missing-key")
def _site_missing_key(case: Path) -> None:
    """No ``targets`` (required): the section is cut out."""
    site = valid_bundle(case) / "site.yaml"
    text = site.read_text()
    start, end = text.index("targets:\n"), text.index("passes:\n")
    site.write_text(text[:start] + text[end:])


@defect("site-wrong-type")
def _site_wrong_type(case: Path) -> None:
    _edit_text(valid_bundle(case) / "site.yaml", "standoff_m: 15.0", "standoff_m: fifteen")


@defect("site-angle-out-of-range")
def _site_angle_out_of_range(case: Path) -> None:
    """T1's inclination 120° (a plane leaning past the vertical: −90 … 90)."""
    _edit_text(valid_bundle(case) / "site.yaml", "inclination_deg: 90.0", "inclination_deg: 120.0")


@defect("site-unknown-key")
def _site_unknown_key(case: Path) -> None:
    """A typo in the mount: ``boresight_deg`` for ``boresight_apriori_deg``."""
    _edit_text(valid_bundle(case) / "site.yaml", "  boresight_apriori_deg:", "  boresight_deg:")


@defect("site-yaml-syntax")
def _site_yaml_syntax(case: Path) -> None:
    """An unclosed flow sequence."""
    _edit_text(
        valid_bundle(case) / "site.yaml",
        "scanner:\n",
        "scanner: [0.003, 0.005\n",
    )


@defect("site-empty-value")
def _site_empty_value(case: Path) -> None:
    """``mount:`` with its three lines gone: an empty value (null), where a mapping belongs."""
    site = valid_bundle(case) / "site.yaml"
    text = site.read_text()
    start, end = text.index("mount:\n") + len("mount:\n"), text.index("scanner:\n")
    site.write_text(text[:start] + text[end:])


@defect("site-no-targets")
def _site_no_targets(case: Path) -> None:
    """``targets: []``: a targetless calibration (architecture §7.9), which this small bundle's few
    tie patches cannot carry: refused, yaw not determined (georeferencing needs no target)."""
    site = valid_bundle(case) / "site.yaml"
    text = site.read_text()
    start, end = text.index("targets:\n"), text.index("passes:\n")
    site.write_text(text[:start] + "targets: []\n" + text[end:])


@defect("site-billion-laughs")
def _site_billion_laughs(case: Path) -> None:
    """Nine levels of nine aliases each: 9⁹ values once expanded, 90 aliases written."""
    text = 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n'
    for i in range(1, 10):
        name, prev = chr(ord("a") + i), chr(ord("a") + i - 1)
        text += f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]\n"
    (valid_bundle(case) / "site.yaml").write_text(text)


@defect("site-is-a-directory")
def _site_is_a_directory(case: Path) -> None:
    site = valid_bundle(case) / "site.yaml"
    site.unlink()
    site.mkdir()


@defect("site-missing")
def _site_missing(case: Path) -> None:
    (valid_bundle(case) / "site.yaml").unlink()


# -- points.csv -------------------------------------------------------------------------------


@defect("points-missing-column")
def _points_missing_column(case: Path) -> None:
    """No ``intensity`` column (header and every line)."""
    p = valid_bundle(case) / "points.csv"
    lines = p.read_text().split("\n")
    p.write_text("\n".join(line.rsplit(",", 1)[0] for line in lines))


@defect("points-non-numeric")
def _points_non_numeric(case: Path) -> None:
    """Line 100's range written with its unit, ``15.2m``."""
    _edit_line(valid_bundle(case) / "points.csv", 100, _set_field(2, "15.2m"))


@defect("points-nan")
def _points_nan(case: Path) -> None:
    """Line 200's gps_time is ``nan``."""
    _edit_line(valid_bundle(case) / "points.csv", 200, _set_field(1, "nan"))


@defect("points-range-out-of-window")
def _points_range_out_of_window(case: Path) -> None:
    """Line 300's range 150 m: beyond the Z+F 9012's 119 m."""
    _edit_line(valid_bundle(case) / "points.csv", 300, _set_field(2, "150.0"))


@defect("points-range-too-short")
def _points_range_too_short(case: Path) -> None:
    """Line 301's range 0.1 m: inside the scanner's 0.3 m dead zone."""
    _edit_line(valid_bundle(case) / "points.csv", 301, _set_field(2, "0.1"))


@defect("points-scan-angle-out-of-window")
def _points_scan_angle_out_of_window(case: Path) -> None:
    """Line 400's scan angle 360° (the window is [0°, 360°))."""
    _edit_line(valid_bundle(case) / "points.csv", 400, _set_field(3, "360"))


@defect("points-negative-scan-angle")
def _points_negative_scan_angle(case: Path) -> None:
    _edit_line(valid_bundle(case) / "points.csv", 401, _set_field(3, "-0.5"))


@defect("points-intensity-out-of-scale")
def _points_intensity_out_of_scale(case: Path) -> None:
    """Line 500's intensity 1.5 in a file of reflectances 0…1."""
    _edit_line(valid_bundle(case) / "points.csv", 500, _set_field(4, "1.5"))


@defect("points-intensity-count-overflow")
def _points_intensity_count_overflow(case: Path) -> None:
    """Counts, one of them (line 600) beyond 16 bits."""
    p = valid_bundle(case) / "points.csv"
    lines = p.read_text().split("\n")
    for i in range(1, len(lines)):
        if lines[i]:
            head, value = lines[i].rsplit(",", 1)
            lines[i] = f"{head},{round(float(value) * 1000)}"
    head = lines[599].rsplit(",", 1)[0]
    lines[599] = f"{head},70000"
    p.write_text("\n".join(lines))


@defect("points-pass-id-overflow")
def _points_pass_id_overflow(case: Path) -> None:
    """Line 2's pass id 2⁶³, one beyond int64 (survey line ids are int64 end to end)."""
    _edit_line(valid_bundle(case) / "points.csv", 2, _set_field(0, str(2**63)))


@defect("points-negative-pass-id")
def _points_negative_pass_id(case: Path) -> None:
    _edit_line(valid_bundle(case) / "points.csv", 3, _set_field(0, "-1"))


@defect("points-time-backwards")
def _points_time_backwards(case: Path) -> None:
    """Lines 700 and 701 swapped: a pass's times go back."""
    p = valid_bundle(case) / "points.csv"
    lines = p.read_text().split("\n")
    lines[699], lines[700] = lines[700], lines[699]
    p.write_text("\n".join(lines))


@defect("points-trailing-comma")
def _points_trailing_comma(case: Path) -> None:
    """A header with a trailing comma (an empty sixth column name)."""
    _edit_text(valid_bundle(case) / "points.csv", "intensity\n", "intensity,\n")


@defect("points-empty")
def _points_empty(case: Path) -> None:
    (valid_bundle(case) / "points.csv").write_bytes(b"")


@defect("points-header-only")
def _points_header_only(case: Path) -> None:
    (valid_bundle(case) / "points.csv").write_text("pass_id,gps_time,range_m,scan_angle_deg,intensity\n")


@defect("points-truncated")
def _points_truncated(case: Path) -> None:
    """The file ends in the middle of its last line (a copy cut short): two characters into
    its range, no newline."""
    p = valid_bundle(case) / "points.csv"
    text = p.read_text().rstrip("\n")
    last = text.rfind("\n") + 1
    cut = text.index(",", text.index(",", last) + 1)
    p.write_text(text[: cut + 3])


@defect("points-bad-gzip")
def _points_bad_gzip(case: Path) -> None:
    """``points.csv.gz`` whose second half is lost."""
    b = valid_bundle(case)
    data = gzip.compress((b / "points.csv").read_bytes(), mtime=0)
    (b / "points.csv").unlink()
    (b / "points.csv.gz").write_bytes(data[: len(data) // 2])


@defect("points-missing")
def _points_missing(case: Path) -> None:
    (valid_bundle(case) / "points.csv").unlink()


# -- trajectory.csv ---------------------------------------------------------------------------


@defect("trajectory-time-backwards")
def _trajectory_time_backwards(case: Path) -> None:
    """Lines 50 and 51 swapped."""
    p = valid_bundle(case) / "trajectory.csv"
    lines = p.read_text().split("\n")
    lines[49], lines[50] = lines[50], lines[49]
    p.write_text("\n".join(lines))


@defect("trajectory-roll-out-of-range")
def _trajectory_roll_out_of_range(case: Path) -> None:
    _edit_line(valid_bundle(case) / "trajectory.csv", 60, _set_field(4, "190.5"))


@defect("trajectory-pitch-out-of-range")
def _trajectory_pitch_out_of_range(case: Path) -> None:
    _edit_line(valid_bundle(case) / "trajectory.csv", 61, _set_field(5, "-95"))


@defect("trajectory-heading-out-of-range")
def _trajectory_heading_out_of_range(case: Path) -> None:
    _edit_line(valid_bundle(case) / "trajectory.csv", 62, _set_field(6, "400"))


@defect("trajectory-gap")
def _trajectory_gap(case: Path) -> None:
    """Epochs 3 s … 5 s after the start missing (2 s without INS, in the middle of pass 1)."""
    p = valid_bundle(case) / "trajectory.csv"
    lines = p.read_text().split("\n")
    t0 = float(lines[1].split(",", 1)[0])
    keep = [line for line in lines[1:] if not line or not 3.0 <= float(line.split(",", 1)[0]) - t0 <= 5.0]
    p.write_text("\n".join([lines[0], *keep]))


@defect("trajectory-missing")
def _trajectory_missing(case: Path) -> None:
    (valid_bundle(case) / "trajectory.csv").unlink()


@defect("trajectory-non-numeric")
def _trajectory_non_numeric(case: Path) -> None:
    _edit_line(valid_bundle(case) / "trajectory.csv", 70, _set_field(3, "high"))


# -- vessel.yaml ------------------------------------------------------------------------------


def valid_vessel(case: Path) -> Path:
    """``case/vessel.yaml``: the example vessel config; its sessions under ``case/sessions``."""
    v = case / "vessel.yaml"
    text = EXAMPLE_VESSEL.read_text()
    v.write_text(text.replace("directory: /var/lib/mls/sessions", f"directory: {case / 'sessions'}"))
    return v


@defect("vessel-unknown-device-kind")
def _vessel_unknown_device_kind(case: Path) -> None:
    _edit_text(valid_vessel(case), "kind: can\n", "kind: canbus\n")


@defect("vessel-bad-port")
def _vessel_bad_port(case: Path) -> None:
    """The profiler's UDP port 70000 (> 65535)."""
    _edit_text(valid_vessel(case), "port: 3000}", "port: 70000}")


@defect("vessel-duplicate-device-name")
def _vessel_duplicate_device_name(case: Path) -> None:
    """The profiler named ``ins`` as well."""
    _edit_text(valid_vessel(case), "- name: profiler ", "- name: ins      ")


@defect("vessel-bad-number")
def _vessel_bad_number(case: Path) -> None:
    """``flush_s: 0,5`` (a decimal comma: a string)."""
    _edit_text(valid_vessel(case), "flush_s: 0.5 ", "flush_s: 0,5 ")


@defect("vessel-yaml-syntax")
def _vessel_yaml_syntax(case: Path) -> None:
    """A tab in the indentation of the session section."""
    _edit_text(valid_vessel(case), "  rotate_s: 600", "\trotate_s: 600")


@defect("vessel-missing-section")
def _vessel_missing_section(case: Path) -> None:
    """No ``session`` section (required)."""
    v = valid_vessel(case)
    text = v.read_text()
    start, end = text.index("session:\n"), text.index("clock:")
    v.write_text(text[:start] + text[end:])


@defect("vessel-empty-section")
def _vessel_empty_section(case: Path) -> None:
    """``mqtt:`` left in place with every line under it commented out (the way to disable MQTT
    is to remove the section)."""
    v = valid_vessel(case)
    text = v.read_text()
    start = text.index("mqtt:")
    head, body = text[:start], text[start:]
    end = body.index("\nmount:")
    lines = body[:end].split("\n")
    body = "\n".join([lines[0]] + ["# " + line for line in lines[1:]]) + body[end:]
    v.write_text(head + body)


@defect("vessel-session-dir-is-a-file")
def _vessel_session_dir_is_a_file(case: Path) -> None:
    valid_vessel(case)  # its sessions in case/sessions: a file here
    (case / "sessions").write_text("not a directory\n")


@defect("vessel-site-file-is-a-directory")
def _vessel_site_file_is_a_directory(case: Path) -> None:
    _edit_text(valid_vessel(case), "# site_file: site.yaml", "site_file: site.yaml")
    (case / "site.yaml").mkdir()


@defect("vessel-is-a-directory")
def _vessel_is_a_directory(case: Path) -> None:
    (case / "vessel.yaml").mkdir()


@defect("vessel-missing")
def _vessel_missing(case: Path) -> None:
    """Nothing at ``case/vessel.yaml``."""


# -- sessions ---------------------------------------------------------------------------------


def valid_session(case: Path) -> Path:
    """``case/session``: the export tests' tiny recorded session (two passes marked, one
    segment), with the site file the daemon would have copied in."""
    from tests.office.jobs.test_export import SITE, _write_session

    written = _write_session(case, marks=True)[0]
    session = case / "session"
    written.rename(session)
    (case / "sessions").rmdir()
    (session / "site.yaml").write_text(SITE)
    return session


@defect("session-no-segments")
def _session_no_segments(case: Path) -> None:
    session = valid_session(case)
    for seg in session.glob("seg-*.mcap"):
        seg.unlink()


@defect("session-garbage-segment")
def _session_garbage_segment(case: Path) -> None:
    """``seg-000001.mcap`` holding bytes that are no MCAP at all."""
    session = valid_session(case)
    (session / "seg-000001.mcap").write_bytes(b"this is not an MCAP file\n" * 40)


@defect("session-torn-segment")
def _session_torn_segment(case: Path) -> None:
    """The segment cut as a crash leaves it: its last 3 kB (summary, footer, the end of the
    last chunk) missing."""
    seg = valid_session(case) / "seg-000001.mcap"
    data = seg.read_bytes()
    seg.write_bytes(data[: len(data) - 3000])


@defect("session-empty-segment")
def _session_empty_segment(case: Path) -> None:
    """The daemon created ``seg-000001.mcap`` and died before writing a byte."""
    (valid_session(case) / "seg-000001.mcap").write_bytes(b"")


@defect("session-bad-summary")
def _session_bad_summary(case: Path) -> None:
    """``session.json`` whose mount has a lever arm of two values."""
    p = valid_session(case) / "session.json"
    p.write_text(p.read_text().replace("[0.35, 0.85, -1.65]", "[0.35, 0.85]"))


@defect("session-bad-site")
def _session_bad_site(case: Path) -> None:
    """The session's copy of the site file has a pass without its heading."""
    _edit_text(valid_session(case) / "site.yaml", "{id: 2, relative_heading_deg: 180.0,", "{id: 2,")


@defect("session-is-a-file")
def _session_is_a_file(case: Path) -> None:
    (case / "session").write_text("not a session\n")


# -- the corpus -------------------------------------------------------------------------------


def build(name: str, root: Path) -> Path:
    """Write defect ``name``'s input into ``root/name`` (created, must not exist); returns it."""
    case = Path(root) / name
    case.mkdir(parents=True)
    DEFECTS[name](case)
    return case


def make_corpus(root: Path, names: list[str] | None = None) -> list[Path]:
    """Write the named defects (default: all) under ``root``."""
    return [build(name, root) for name in (names or list(DEFECTS))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tests.corpus.make_corpus", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("out", type=Path, help="directory to write the corpus into (one folder per defect)")
    parser.add_argument("defects", nargs="*", help=f"defects to write (default all {len(DEFECTS)})")
    args = parser.parse_args(argv)
    unknown = [d for d in args.defects if d not in DEFECTS]
    if unknown:
        parser.error(f"unknown defect {unknown[0]!r}; known: {', '.join(DEFECTS)}")
    taken = [d for d in args.defects or DEFECTS if (args.out / d).exists()]
    if taken:
        parser.error(f"{args.out / taken[0]} exists: choose an empty directory")
    for case in make_corpus(args.out, args.defects or None):
        print(case)
    return 0


if __name__ == "__main__":
    sys.exit(main())

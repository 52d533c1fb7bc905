"""What each command answers to each malformed input of the corpus (``make_corpus.DEFECTS``):
the exit status and the first line of the message, decided by running the CLI on every case and
reading what it printed (a traceback, or a message that did not name the file, line or field,
was fixed in the library first).

``{case}`` in the arguments and the expected line stands for the case's directory (the defect's
folder that ``make_corpus.build`` writes: ``bundle/``, ``vessel.yaml`` or ``session/`` in it).
An expected line is exact text unless ``regex`` is set: then the line must match it whole
(``{case}`` replaced by the escaped directory), for numbers the writer or the example bundle decide (byte counts, times).
"""

from __future__ import annotations

from dataclasses import dataclass

from calib.boresight.checks.verdict import REFUSED_EXIT_STATUS


@dataclass(frozen=True)
class Case:
    defect: str  # a key of make_corpus.DEFECTS
    argv: tuple[str, ...]  # mls arguments
    status: int  # expected exit status
    first_line: str  # expected first line of stderr
    regex: bool = False
    subprocess: bool = False  # also run through the console entry point (python -m cli.app)

    @property
    def command(self) -> str:
        """``calib run``, ``calib georef``, ``export`` or ``acquire --check``."""
        return " ".join(self.argv[:2]) if self.argv[0] in ("calib", "acquire") else self.argv[0]

    @property
    def id(self) -> str:
        return f"{self.defect}:{self.command.replace(' --', '-').replace(' ', '-')}"


CALIB_RUN = ("calib", "run", "{case}/bundle", "--out", "{case}/calib", "--no-history", "--no-plots")
GEOREF = ("calib", "georef", "{case}/bundle", "--out", "{case}/laz")
CHECK = ("acquire", "--check", "--config", "{case}/vessel.yaml")
EXPORT = ("export", "{case}/session", "--bundle", "{case}/out")

# exit statuses (docs/architecture.md §9.3)
CALIB_FAILED = 1  # mls calib run: a bundle that cannot be calibrated; georef: MlsGroup
CONFIG_INVALID = 2  # mls acquire: an invalid vessel config
EXPORT_FAILED = 1


def _bundle(defect: str, line: str, regex: bool = False, georef: str | None = None, **kw) -> list[Case]:
    """The same defect through ``mls calib run`` and ``mls calib georef`` (which read a bundle
    alike): the same first line unless ``georef`` gives its own."""
    return [
        Case(defect, CALIB_RUN, CALIB_FAILED, line, regex, **kw),
        Case(defect, GEOREF, CALIB_FAILED, line if georef is None else georef, regex),
    ]


SITE = "{case}/bundle/site.yaml"
POINTS = "{case}/bundle/points.csv"
TRAJ = "{case}/bundle/trajectory.csv"
HEADER = "pass_id,gps_time,range_m,scan_angle_deg,intensity"
T = r"\d{10}\.\d+"  # a GPS time in seconds, as a message prints it

CASES: list[Case] = [
    # -- site.yaml ------------------------------------------------------------------------------
    *_bundle("site-missing-key", f"error: {SITE}:1:1: <top level>: missing required key 'targets'"),
    *_bundle("site-wrong-type", f"error: {SITE}:32:13: standoff_m: got 'fifteen', expected a finite number"),
    *_bundle(
        "site-angle-out-of-range",
        f"error: {SITE}:42:20: targets[0].inclination_deg: got 120.0, expected a number ≤ 90",
    ),
    *_bundle(
        "site-unknown-key",
        f"error: {SITE}:16:3: mount.boresight_deg: unknown key 'boresight_deg'; allowed keys here: "
        f"boresight_apriori_deg, lever_arm_m, nominal_deg",
    ),
    *_bundle("site-yaml-syntax", f"error: {SITE}:20:16: not valid YAML: expected ',' or ']', but got ':'"),
    *_bundle("site-empty-value", f"error: {SITE}:6:7: mount: got None, expected a mapping"),
    Case(
        "site-no-targets",
        CALIB_RUN,
        REFUSED_EXIT_STATUS,
        r"error: verdict refused: the result in {case}/calib must not be used \(see report\.md\); it "
        r"was not recorded in the history\. --accept-refused records it anyway, marked",
        regex=True,
    ),  # a targetless calibration (architecture §7.9): this site's few patches leave yaw free
    *_bundle(
        "site-billion-laughs",
        f"error: {SITE}: more than 100,000 values once its aliases are expanded (aliases nested in "
        f"aliases, a 'billion laughs'?): refused",
    ),
    *_bundle("site-is-a-directory", f"error: {SITE}: is a directory, expected a YAML file"),
    *_bundle("site-missing", f"error: {SITE}: file not found"),
    # -- points.csv -----------------------------------------------------------------------------
    *_bundle(
        "points-missing-column",
        f"error: {POINTS}:1: header is 'pass_id,gps_time,range_m,scan_angle_deg', expected it to "
        f"start with '{HEADER}'",
    ),
    *_bundle(
        "points-trailing-comma",
        f"error: {POINTS}:1: unexpected columns '' (an empty column name: a trailing comma?); after "
        f"'{HEADER}' no other column may follow",
    ),
    *_bundle(
        "points-non-numeric",
        f"error: {POINTS}:100:3: column 'range_m' is '15.2m', expected a number",
        subprocess=True,  # ":100:" stays itself through rich (no emoji)
    ),
    *_bundle("points-nan", f"error: {POINTS}:200:2: column 'gps_time' is 'nan', expected a finite number"),
    *_bundle(
        "points-range-out-of-window",
        f"error: {POINTS}:300:3: range_m is 150.0, expected 0.3…119 m (the Z+F 9012's range window)",
    ),
    *_bundle(
        "points-range-too-short",
        f"error: {POINTS}:301:3: range_m is 0.1, expected 0.3…119 m (the Z+F 9012's range window)",
    ),
    *_bundle(
        "points-scan-angle-out-of-window",
        f"error: {POINTS}:400:4: scan_angle_deg is 360.0, expected 0 ≤ angle < 360 (the scanner's full circle)",
    ),
    *_bundle(
        "points-negative-scan-angle",
        f"error: {POINTS}:401:4: scan_angle_deg is -0.5, expected 0 ≤ angle < 360 (the scanner's full circle)",
    ),
    *_bundle(
        "points-intensity-out-of-scale",
        f"error: {POINTS}:500:5: intensity is 1.5, expected 0…1: the file holds fractions (line 2: "
        f"0.35), read as reflectances 0…1; counts must all be whole numbers 0…65535. One scale per "
        f"file: fix the value or the file",
    ),
    *_bundle(
        "points-intensity-count-overflow",
        f"error: {POINTS}:600:5: intensity is 70000.0, expected 0…65535: the file holds whole numbers "
        f"beyond 0…1, read as counts (16 bits)",
    ),
    *_bundle(
        "points-pass-id-overflow",
        f"error: {POINTS}:2:1: pass_id is 9223372036854775808, expected a non-negative integer ≤ "
        f"9223372036854775807",
    ),
    *_bundle(
        "points-negative-pass-id", f"error: {POINTS}:3:1: pass_id is -1.0, expected a non-negative integer"
    ),
    *_bundle(
        "points-time-backwards",
        rf"error: {{case}}/bundle/points\.csv:701:2: gps_time {T} follows {T}; times must not "
        rf"decrease within a pass",
        regex=True,
    ),
    *_bundle(
        "points-empty",
        f"error: {POINTS}: empty file, expected a header line '{HEADER}' and data lines",
    ),
    *_bundle("points-header-only", f"error: {POINTS}: no points"),
    *_bundle("points-truncated", f"error: {POINTS}:15755: 3 fields, expected 5 ({HEADER})"),
    *_bundle(
        "points-bad-gzip",
        f"error: {POINTS}.gz: not a valid gzip file (Compressed file ended before the end-of-stream "
        f"marker was reached)",
    ),
    *_bundle("points-missing", "error: {case}/bundle: no points.csv or points.csv.gz"),
    # -- trajectory.csv -------------------------------------------------------------------------
    *_bundle(
        "trajectory-time-backwards",
        rf"error: {{case}}/bundle/trajectory\.csv:51:1: gps_time {T} follows {T}; times must increase strictly",
        regex=True,
    ),
    *_bundle("trajectory-roll-out-of-range", f"error: {TRAJ}:60:5: roll_deg is 190.5, expected -180…180"),
    *_bundle("trajectory-pitch-out-of-range", f"error: {TRAJ}:61:6: pitch_deg is -95.0, expected -90…90"),
    *_bundle(
        "trajectory-heading-out-of-range", f"error: {TRAJ}:62:7: heading_deg is 400.0, expected -360…360"
    ),
    *_bundle("trajectory-non-numeric", f"error: {TRAJ}:70:4: column 'height_m' is 'high', expected a number"),
    *_bundle(
        "trajectory-gap",
        rf"error: the trajectory does not cover the points: {{case}}/bundle/trajectory\.csv spans "
        rf"{T}…{T} s \(gaps > 1 s refused\); pass 1: \d+ of 7877 points, {T}…{T} s \(\d+ in the gap "
        rf"{T} … {T} s \(2\.0\d\d s\)\)\. Export the trajectory over every pass, or drop these points "
        rf"with --skip-uncovered \(mls calib run\)\.",
        regex=True,
        georef=(
            rf"error: {{case}}/bundle/points\.csv: pass 1: \d+ of 7877 points fall outside the "
            rf"trajectory {{case}}/bundle/trajectory\.csv \({T} … {T} s\) or in a gap > 1 s \(first "
            rf"{T} s, last {T} s: \d+ in the gap {T} … {T} s \(2\.0\d\d s\)\); use --skip-uncovered "
            rf"to drop them"
        ),
    ),
    *_bundle("trajectory-missing", "error: {case}/bundle: no trajectory.csv or trajectory.sbet"),
    # -- vessel.yaml (mls acquire --check): every error on its own line, then a count ------------
    Case(
        "vessel-unknown-device-kind",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:39:11: devices[3].kind: got 'canbus', expected one of ins, profiler, pps, can",
        subprocess=True,
    ),
    Case(
        "vessel-bad-port",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:28:49: devices[1].transport.port: got 70000, expected an integer between 1 and 65535",
    ),
    Case(
        "vessel-duplicate-device-name",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:25:11: devices[1].name: device name 'ins' is used twice (first at devices[0].name)",
    ),
    Case(
        "vessel-bad-number",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:46:12: session.flush_s: got '0,5', expected a finite number",
    ),
    Case(
        "vessel-yaml-syntax",
        CHECK,
        CONFIG_INVALID,
        "mls acquire: {case}/vessel.yaml:44:1: not valid YAML: found character '\\t' that cannot start any token",
    ),
    Case(
        "vessel-missing-section",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:6:1: <top level>: missing required key 'session'",
    ),
    Case(
        "vessel-empty-section",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:68:6: mqtt: got None, expected a mapping",
    ),
    Case(
        "vessel-session-dir-is-a-file",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:43:14: session.directory: got '{case}/sessions', expected a directory for "
        "the sessions ({case}/sessions is a file)",
    ),
    Case(
        "vessel-site-file-is-a-directory",
        CHECK,
        CONFIG_INVALID,
        "{case}/vessel.yaml:88:12: site_file: got 'site.yaml', expected an existing site file "
        "({case}/site.yaml is a directory)",
    ),
    Case(
        "vessel-is-a-directory",
        CHECK,
        CONFIG_INVALID,
        "mls acquire: {case}/vessel.yaml: is a directory, expected a YAML file",
    ),
    Case("vessel-missing", CHECK, CONFIG_INVALID, "mls acquire: {case}/vessel.yaml: file not found"),
    # -- sessions (mls export) ------------------------------------------------------------------
    Case(
        "session-no-segments",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session: no segments (seg-NNNNNN.mcap)",
    ),
    Case(
        "session-garbage-segment",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session: nothing to export, no segment holds a complete message: seg-000001.mcap "
        "is not an MCAP file (its 1000 bytes do not start with the MCAP magic): none of its messages "
        "is in the export",
        subprocess=True,
    ),
    Case(
        "session-empty-segment",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session: nothing to export, no segment holds a complete message: seg-000001.mcap "
        "is unfinished (empty file): none of its messages is in the export",
    ),
    Case(
        "session-torn-segment",
        (*EXPORT, "--require-complete"),
        EXPORT_FAILED,
        r"error: {case}/session: incomplete session, not exported \(--require-complete\): "
        r"seg-000001\.mcap is unfinished \(\d+ torn bytes, torn [a-z_]+ record at byte \d+ \(\d+ bytes "
        r"announced, \d+ present\)\): messages after \d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} UTC are lost "
        r"\(how long the recording went on is unknown\)",
        regex=True,
    ),
    Case(
        "session-bad-summary",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session/session.json: mount.lever_arm_m: got [0.35, 0.85], expected a list of 3 numbers",
    ),
    Case(
        "session-bad-site",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session/site.yaml:10:5: passes[1]: missing required key 'relative_heading_deg'",
    ),
    Case(
        "session-is-a-file",
        EXPORT,
        EXPORT_FAILED,
        "error: {case}/session: not a directory (a session is the directory the daemon recorded)",
    ),
]

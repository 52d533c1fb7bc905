"""The calibration bundle (docs/architecture.md §4): the interchange directory between simulation, export and
calibration.

    BUNDLE/site.yaml          site config (reference, mount, sigmas, targets, passes)
    BUNDLE/trajectory.csv     gps_time,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,heading_deg
                              [,sigma_north_m,sigma_east_m,sigma_down_m,
                                sigma_roll_deg,sigma_pitch_deg,sigma_heading_deg]
                              (or trajectory.sbet [+ trajectory.smrmsg], see calib.io.sbet)
    BUNDLE/points.csv[.gz]    pass_id,gps_time,range_m,scan_angle_deg,intensity
    BUNDLE/truth.json         simulated bundles only; never read by ``mls calib run``

Every error names the file, the line and the column and what was expected.

``points.csv`` values are checked, not trusted (docs/architecture.md §4.3):

- ``pass_id``: a non-negative integer up to 2⁶³ − 1, kept as int64 end to end (survey line ids
  such as 20240709001 do not fit 32 bits; ids above 2⁵³ are re-read as exact integers);
- ``range_m`` and ``scan_angle_deg`` inside the scanner's physical window,
  :data:`SCANNER_RANGE_M` (0.3 … 119 m) and :data:`SCAN_ANGLE_DEG` ([0°, 360°)) of the Z+F
  Profiler 9012: a value outside is an error naming its line, never a point;
- ``intensity``: one scale per file, decided from the whole file and stated
  (:func:`intensity_scale`): reflectances (every value in 0 … 1) or counts (every value an
  integer in 0 … 65535). A value that breaks the file's scale is an error naming its line: one
  stray value never rescales, or is clipped in, the other values silently.
"""

from __future__ import annotations

import gzip
import io
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError, read_file
from calib.core.trajectory import Trajectory, TrajectoryError
from calib.io.configfile import ConfigError
from calib.io.outputs import make_output_dir
from calib.io.site import Site, load_site

TRAJECTORY_COLUMNS = ("gps_time", "lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "heading_deg")
TRAJECTORY_SIGMA_COLUMNS = (
    "sigma_north_m",
    "sigma_east_m",
    "sigma_down_m",
    "sigma_roll_deg",
    "sigma_pitch_deg",
    "sigma_heading_deg",
)
#: (column index, name, lowest, highest) of the trajectory.csv values with a range.
TRAJECTORY_RANGES = (
    (1, "lat_deg", -90, 90),
    (2, "lon_deg", -180, 360),
    (4, "roll_deg", -180, 180),
    (5, "pitch_deg", -90, 90),
    (6, "heading_deg", -360, 360),
)
POINT_COLUMNS = ("pass_id", "gps_time", "range_m", "scan_angle_deg", "intensity")
#: The physical measurement window of the Z+F Profiler 9012: ranges (m, both ends included) and
#: scan angles (deg, [low, high)); the simulator's scanner model (``calib.sim.scenario``) and its
#: angular recording windows lie inside it.
SCANNER_RANGE_M = (0.3, 119.0)
SCAN_ANGLE_DEG = (0.0, 360.0)
INTENSITY_COUNTS_MAX = 65535
PASS_ID_MAX = 2**63 - 1  # int64
_EXACT_FLOAT_INT = 2**53  # above it a float64 no longer holds every integer


class BundleError(CalibError, ValueError):
    """A bundle file is missing or malformed (the message names file, line and column)."""


@dataclass(frozen=True)
class ScanPoints:
    """Raw scanner observations, one entry per return."""

    pass_id: np.ndarray  # int64 (survey line ids exceed 32 bits)
    t_gps_s: np.ndarray  # float64 seconds since the GPS epoch
    range_m: np.ndarray
    scan_angle_rad: np.ndarray
    intensity: np.ndarray  # float32

    def __post_init__(self):
        n = np.asarray(self.t_gps_s).shape[0]
        for name, dtype in (
            ("pass_id", np.int64),
            ("t_gps_s", np.float64),
            ("range_m", np.float64),
            ("scan_angle_rad", np.float64),
            ("intensity", np.float32),
        ):
            a = np.asarray(getattr(self, name), dtype=dtype)
            if a.shape != (n,):
                raise ValueError(f"ScanPoints.{name} has shape {a.shape}, expected ({n},)")
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return self.t_gps_s.shape[0]

    def select(self, mask) -> ScanPoints:
        return ScanPoints(
            self.pass_id[mask],
            self.t_gps_s[mask],
            self.range_m[mask],
            self.scan_angle_rad[mask],
            self.intensity[mask],
        )

    @staticmethod
    def concatenate(parts: list[ScanPoints]) -> ScanPoints:
        return ScanPoints(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("pass_id", "t_gps_s", "range_m", "scan_angle_rad", "intensity")
            )
        )

    def pass_ids(self) -> list[int]:
        return [int(p) for p in np.unique(self.pass_id)]


@dataclass(frozen=True)
class Bundle:
    path: Path
    site: Site
    trajectory: Trajectory
    points: ScanPoints

    @property
    def frame(self) -> frames.LocalFrame:
        return self.trajectory.frame

    @property
    def points_path(self) -> Path:
        return _points_path(self.path)

    def pass_warnings(self) -> list[str]:
        """The passes planned in site.yaml without points, and the points of unplanned passes."""
        return pass_warnings(self.site, self.points.pass_id, self.path / "site.yaml", self.points_path)


@dataclass(frozen=True)
class IntensityScale:
    """How a file's intensities become LAS's 16-bit intensity (:func:`intensity_scale`)."""

    kind: str  # "reflectance" (0 … 1) or "counts" (integers 0 … 65535)
    factor: float  # multiplies the values into 0 … 65535

    @property
    def meaning(self) -> str:
        return "reflectances 0…1" if self.kind == "reflectance" else "counts 0…65535"

    def describe(self) -> str:
        """The scale as LAS gets it."""
        return "reflectance 0…1, ×65535" if self.kind == "reflectance" else "counts 0…65535, as they are"


# -- CSV ------------------------------------------------------------------------------------


def _open_text(path: Path) -> str:
    raw = read_file(path, BundleError)
    if path.suffix == ".gz":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as e:
            raise BundleError(f"{path}: not a valid gzip file ({e})") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise BundleError(f"{path}:{line}: not UTF-8 text") from None


def _fast_floats(body: str, n_lines: int, k: int) -> np.ndarray | None:
    """The (n_lines, k) numbers of ``body``, or None unless every line holds k finite numbers.

    Every line end is parsed as an extra ``inf`` field, so that a line with a missing field
    next to a line with an extra one cannot pass for two good lines.
    """
    text = (body if body.endswith("\n") else body + "\n").replace("\n", ",inf,")[:-1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            values = np.fromstring(text, sep=",")
        except ValueError:
            return None
    if values.size != n_lines * (k + 1):
        return None
    values = values.reshape(n_lines, k + 1)
    if not (np.all(np.isinf(values[:, k])) and np.all(np.isfinite(values[:, :k]))):
        return None
    return values[:, :k]


def _parse_csv(
    path: Path, text: str, required: tuple[str, ...], optional: tuple[str, ...] = ()
) -> tuple[list[str], np.ndarray]:
    """Parse a numeric CSV with a header; returns (columns, (n, k) float64 array).

    A fast C-level parse is tried first; when it fails, a line-by-line pass finds the first bad
    line and column for the error message.
    """
    header_end = text.find("\n")
    header = (text if header_end < 0 else text[:header_end]).strip().lstrip("\ufeff")
    if not text.strip():
        raise BundleError(f"{path}: empty file, expected a header line {','.join(required)!r} and data lines")
    columns = [c.strip() for c in header.split(",")]
    if columns[: len(required)] != list(required):
        raise BundleError(f"{path}:1: header is {header!r}, expected it to start with {','.join(required)!r}")
    extra = columns[len(required) :]
    if extra and extra != list(optional):
        names = f"{','.join(extra)!r}" + ("" if all(extra) else " (an empty column name: a trailing comma?)")
        may_follow = f"only {','.join(optional)!r} may follow" if optional else "no other column may follow"
        raise BundleError(f"{path}:1: unexpected columns {names}; after {','.join(required)!r} {may_follow}")
    k = len(columns)
    body = "" if header_end < 0 else text[header_end + 1 :]
    body = body.replace("\r", "")
    n_lines = body.count("\n") + (0 if body.endswith("\n") or not body else 1)
    if n_lines == 0:
        return columns, np.empty((0, k))
    values = _fast_floats(body, n_lines, k)
    if values is not None:
        return columns, values
    _raise_first_bad_line(path, body, n_lines, columns)
    raise BundleError(f"{path}: could not parse as CSV with columns {','.join(columns)}")


def _raise_first_bad_line(path: Path, body: str, n_lines: int, columns: list[str]) -> None:
    """The slow path of :func:`_parse_csv`: a :class:`BundleError` naming the first bad line
    and column (returns when it finds none)."""
    k = len(columns)
    for i, line in enumerate(body.split("\n")):
        if not line and i == n_lines:
            break
        if not line.strip():
            raise BundleError(f"{path}:{i + 2}: empty line, expected {k} fields ({','.join(columns)})")
        fields = line.split(",")
        if len(fields) != k:
            raise BundleError(f"{path}:{i + 2}: {len(fields)} fields, expected {k} ({','.join(columns)})")
        for j, f in enumerate(fields):
            try:
                v = float(f)
            except ValueError:
                raise BundleError(
                    f"{path}:{i + 2}:{j + 1}: column {columns[j]!r} is {f!r}, expected a number"
                ) from None
            if not np.isfinite(v):
                raise BundleError(
                    f"{path}:{i + 2}:{j + 1}: column {columns[j]!r} is {f!r}, expected a finite number"
                )


def _write_csv(path: Path, header: tuple[str, ...], fmt: str, cols: list[np.ndarray]) -> None:
    line = ",".join(fmt.split(",")) + "\n"
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    rows = zip(*[c.tolist() for c in cols], strict=False)
    buf.write("".join(line % r for r in rows))
    data = buf.getvalue().encode("utf-8")
    if path.suffix == ".gz":
        data = gzip.compress(data, compresslevel=6, mtime=0)  # mtime=0: reproducible bytes
    path.write_bytes(data)


def _check_sorted_column(
    path: Path, values: np.ndarray, column: str, col_index: int, group: np.ndarray | None = None
) -> None:
    if values.size < 2:
        return
    d = np.diff(values)
    bad = d <= 0 if group is None else (d < 0) & (group[1:] == group[:-1])
    if np.any(bad):
        i = int(np.argmax(bad)) + 1
        what = "increase strictly" if group is None else "not decrease within a pass"
        raise BundleError(
            f"{path}:{i + 2}:{col_index + 1}: {column} {float(values[i])!r} follows "
            f"{float(values[i - 1])!r}; times must {what}"
        )


def read_trajectory_csv(
    path: Path, frame: frames.LocalFrame | None = None, max_gap_s: float = 1.0
) -> Trajectory:
    path = Path(path)
    columns, a = _parse_csv(path, _open_text(path), TRAJECTORY_COLUMNS, TRAJECTORY_SIGMA_COLUMNS)
    if a.shape[0] < 2:
        raise BundleError(f"{path}: {a.shape[0]} trajectory epochs, expected at least 2")
    _check_sorted_column(path, a[:, 0], "gps_time", 0)
    for j, name, lo, hi in TRAJECTORY_RANGES:
        bad = ~((a[:, j] >= lo) & (a[:, j] <= hi))
        if bad.any():
            i = int(np.argmax(bad))
            raise BundleError(f"{path}:{i + 2}:{j + 1}: {name} is {float(a[i, j])!r}, expected {lo}…{hi}")
    sig_p = sig_a = None
    if len(columns) > len(TRAJECTORY_COLUMNS):
        sig = a[:, 7:]
        bad = sig <= 0
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise BundleError(
                f"{path}:{i + 2}:{j + 8}: {columns[j + 7]} is {float(sig[i, j])!r}, expected a positive sigma"
            )
        sig_p, sig_a = sig[:, :3], np.radians(sig[:, 3:])
    try:
        return Trajectory.from_geodetic(
            a[:, 0],
            a[:, 1],
            a[:, 2],
            a[:, 3],
            np.radians(a[:, 4:7]),
            frame,
            sigma_p_m=sig_p,
            sigma_rpy_rad=sig_a,
            max_gap_s=max_gap_s,
            name=str(path),
        )
    except TrajectoryError as e:
        raise BundleError(str(e)) from None


def write_trajectory_csv(path: Path, traj: Trajectory) -> None:
    lat, lon, h = traj.geodetic()
    rpy = np.degrees(traj.rpy_rad)
    cols = [traj.t_gps_s, lat, lon, h, rpy[:, 0], rpy[:, 1], rpy[:, 2]]
    header: tuple[str, ...] = TRAJECTORY_COLUMNS
    fmt = "%.9f,%.12f,%.12f,%.6f,%.12g,%.12g,%.12g"
    sp, srpy = traj.sigma_p_m, traj.sigma_rpy_rad
    if sp is not None and srpy is not None:  # traj.has_sigmas
        sa = np.degrees(srpy)
        cols += [
            sp[:, 0],
            sp[:, 1],
            sp[:, 2],
            sa[:, 0],
            sa[:, 1],
            sa[:, 2],
        ]
        header = header + TRAJECTORY_SIGMA_COLUMNS
        fmt += ",%.6g,%.6g,%.6g,%.6g,%.6g,%.6g"
    _write_csv(Path(path), header, fmt, cols)


def _first_bad(bad: np.ndarray) -> int | None:
    return int(np.argmax(bad)) if bad.any() else None


def _exact_pass_ids(path: Path, text: str, n: int) -> np.ndarray:
    """The pass_id column read as integers (for ids above 2⁵³, where float64 rounds)."""
    body = text[text.find("\n") + 1 :].replace("\r", "").split("\n")[:n]
    out = np.empty(n, np.int64)
    for i, line in enumerate(body):
        field = line.split(",", 1)[0].strip()
        try:
            v = int(field)
        except ValueError:
            v = int(float(field))  # "20240709001.0": the float check already found it whole
        if not 0 <= v <= PASS_ID_MAX:
            raise BundleError(
                f"{path}:{i + 2}:1: pass_id is {field}, expected a non-negative integer ≤ {PASS_ID_MAX}"
            )
        out[i] = v
    return out


def intensity_scale(intensity: np.ndarray, path: Path | str = "points.csv") -> IntensityScale:
    """The one intensity scale of a file, from all its values (module docstring): reflectances
    when every value is in 0 … 1, else counts when every value is an integer, each in 0 … 65535.
    A value that fits neither is a :class:`BundleError` naming its line (row i is line i + 2)."""
    v = np.asarray(intensity, dtype=np.float64)
    if v.size == 0 or ((v >= 0.0) & (v <= 1.0)).all():
        return IntensityScale("reflectance", float(INTENSITY_COUNTS_MAX))
    fractional = v != np.round(v)
    if not fractional.any():
        i = _first_bad((v < 0) | (v > INTENSITY_COUNTS_MAX))
        if i is not None:
            raise BundleError(
                f"{path}:{i + 2}:5: intensity is {float(v[i])!r}, expected 0…{INTENSITY_COUNTS_MAX}: "
                f"the file holds whole numbers beyond 0…1, read as counts (16 bits)"
            )
        return IntensityScale("counts", 1.0)
    j = int(np.argmax(fractional))
    i = int(np.argmax((v < 0.0) | (v > 1.0)))
    raise BundleError(
        f"{path}:{i + 2}:5: intensity is {float(v[i])!r}, expected 0…1: the file holds fractions "
        f"(line {j + 2}: {float(v[j])!r}), read as reflectances 0…1; counts must all be whole "
        f"numbers 0…{INTENSITY_COUNTS_MAX}. One scale per file: fix the value or the file"
    )


def read_points_csv(path: Path) -> ScanPoints:
    """points.csv(.gz), every value checked (module docstring); errors name file:line:column."""
    path = Path(path)
    text = _open_text(path)
    _, a = _parse_csv(path, text, POINT_COLUMNS)
    if a.shape[0] == 0:
        raise BundleError(f"{path}: no points")
    pid = a[:, 0]
    i = _first_bad((pid != np.round(pid)) | (pid < 0))
    if i is not None:
        raise BundleError(f"{path}:{i + 2}:1: pass_id is {float(pid[i])!r}, expected a non-negative integer")
    if (pid >= _EXACT_FLOAT_INT).any():
        ids = _exact_pass_ids(path, text, a.shape[0])
    else:
        ids = pid.astype(np.int64)
    lo, hi = SCANNER_RANGE_M
    i = _first_bad(~((a[:, 2] >= lo) & (a[:, 2] <= hi)))
    if i is not None:
        raise BundleError(
            f"{path}:{i + 2}:3: range_m is {float(a[i, 2])!r}, expected {lo:g}…{hi:g} m "
            f"(the Z+F 9012's range window)"
        )
    lo, hi = SCAN_ANGLE_DEG
    i = _first_bad(~((a[:, 3] >= lo) & (a[:, 3] < hi)))
    if i is not None:
        raise BundleError(
            f"{path}:{i + 2}:4: scan_angle_deg is {float(a[i, 3])!r}, expected {lo:g} ≤ angle < "
            f"{hi:g} (the scanner's full circle)"
        )
    intensity_scale(a[:, 4], path)  # one scale for the file, or the line that breaks it
    _check_sorted_column(path, a[:, 1], "gps_time", 1, group=ids)
    return ScanPoints(ids, a[:, 1], a[:, 2], np.radians(a[:, 3]), a[:, 4])


def write_points_csv(path: Path, pts: ScanPoints) -> None:
    """points.csv(.gz); scan angles are written in [0°, 360°) (the same directions)."""
    deg = np.mod(np.degrees(pts.scan_angle_rad), 360.0)
    deg[deg >= 360.0] = 0.0  # a tiny negative angle rounds up to 360
    _write_csv(
        Path(path),
        POINT_COLUMNS,
        "%d,%.9f,%.17g,%.17g,%.6g",
        [pts.pass_id, pts.t_gps_s, pts.range_m, deg, pts.intensity],
    )


def pass_warnings(
    site: Site, pass_id: np.ndarray, site_path: Path | str, points_path: Path | str
) -> list[str]:
    """Warnings (naming both files) for the passes ``site`` plans that have no points and for
    points of passes it does not plan."""
    ids, counts = np.unique(np.asarray(pass_id, dtype=np.int64), return_counts=True)
    have = {int(k): int(n) for k, n in zip(ids, counts, strict=False)}
    planned = [p.id for p in site.passes]
    plan = "" if site.passes_listed else " (it lists no passes: the default six-fold plan, ids 1–6)"
    out = []
    missing = [p for p in planned if p not in have]
    if missing:
        s = "" if len(missing) == 1 else "es"
        out.append(
            f"pass{s} {', '.join(map(str, missing))} planned in {site_path}{plan} "
            f"{'has' if len(missing) == 1 else 'have'} no points in {points_path}"
        )
    extra = [p for p in have if p not in set(planned)]
    if extra:
        listed = ", ".join(f"{p} ({have[p]:,} points)" for p in extra)
        s = "" if len(extra) == 1 else "es"
        out.append(f"{points_path} holds points of pass{s} {listed} not planned in {site_path}{plan}")
    return out


# -- the bundle -----------------------------------------------------------------------------


def _points_path(d: Path) -> Path:
    for name in ("points.csv", "points.csv.gz"):
        if (d / name).exists():
            return d / name
    raise BundleError(f"{d}: no points.csv or points.csv.gz")


def read_bundle(path: str | Path, max_gap_s: float = 1.0) -> Bundle:
    """Read a bundle directory; the LGF is the site's reference, else the trajectory mean."""
    d = Path(path)
    if not d.is_dir():
        raise BundleError(
            f"{d}: not a directory (a calibration bundle is a directory with "
            f"site.yaml, trajectory.csv and points.csv)"
        )
    try:
        site = load_site(d / "site.yaml")
    except ConfigError as e:
        raise BundleError(str(e)) from None
    points = read_points_csv(_points_path(d))
    if (d / "trajectory.csv").exists():
        traj = read_trajectory_csv(d / "trajectory.csv", site.reference, max_gap_s)
    elif (d / "trajectory.sbet").exists():
        from calib.io.sbet import SbetError, read_sbet_trajectory

        smrmsg = d / "trajectory.smrmsg"
        try:  # SBET times are seconds of the week: the week is the one of the points
            traj = read_sbet_trajectory(
                d / "trajectory.sbet",
                site.reference,
                max_gap_s,
                near_gps_s=float(points.t_gps_s[0]),
                smrmsg_path=smrmsg if smrmsg.exists() else None,
            )
        except SbetError as e:
            raise BundleError(str(e)) from None
    else:
        raise BundleError(f"{d}: no trajectory.csv or trajectory.sbet")
    return Bundle(d, site, traj, points)


def write_bundle(
    path: str | Path,
    site: Site,
    trajectory: Trajectory,
    points: ScanPoints,
    truth: dict | None = None,
    compress_points: bool = False,
) -> Path:
    """Write a bundle directory (created if needed; bundle files already there replaced,
    stale ones removed: the commands check first, :mod:`calib.io.outputs`); returns its path."""
    d = make_output_dir(path, "the bundle directory")
    # a bundle file this one does not write would be read with it: another dataset's truth,
    # an SBET trajectory, the other points file
    for stale in ("points.csv", "points.csv.gz", "trajectory.sbet", "trajectory.smrmsg", "truth.json"):
        (d / stale).unlink(missing_ok=True)
    site.dump(d / "site.yaml")
    write_trajectory_csv(d / "trajectory.csv", trajectory)
    write_points_csv(d / ("points.csv.gz" if compress_points else "points.csv"), points)
    if truth is not None:
        (d / "truth.json").write_text(json.dumps(truth, indent=2, sort_keys=True) + "\n")
    return d


def read_truth(path: str | Path) -> dict:
    """The injected errors of a simulated bundle (tests and assessment only)."""
    p = Path(path) / "truth.json"
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise BundleError(f"{p}: not found (only simulated bundles carry a truth)") from None
    except IsADirectoryError:
        raise BundleError(f"{p}: is a directory, expected a file") from None
    except json.JSONDecodeError as e:
        raise BundleError(f"{p}:{e.lineno}:{e.colno}: not valid JSON ({e.msg})") from None

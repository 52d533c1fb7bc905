"""Calibration history: every boresight result in a local SQLite database, and the test whether
two calibrations differ (thesis §4.5.5: the mount moved between July and October 2019).

The database (stdlib ``sqlite3``) is ``$MLS_HISTORY_DB`` when set, else
``$XDG_DATA_HOME/marine-mls/history.sqlite`` (``~/.local/share/marine-mls/history.sqlite``);
every function takes ``db=`` to override both. One row per recorded result: vessel, mount id,
survey date (UTC, from the bundle's first trajectory epoch when it has a ``trajectory.csv``),
recording date, the boresight estimates, formal / scaled / realistic σ, correlation, σ̂0²,
number of points, software version, the bundle's path and fingerprint (each in its own column,
for anyone reading the database with sqlite3), and the whole result.json. Recording the same result of the same bundle twice returns the first row's id.

The **bundle fingerprint** is a SHA-256 over the bundle's input files (site.yaml, the trajectory
— trajectory.csv or trajectory.sbet [+ .smrmsg] —, points.csv[.gz]), each as name, size and
bytes, in that order; ``truth.json`` and outputs are left out, so re-running the same bundle is
recognised.

**Comparing** two results: per angle, ``Δ = b − a`` against ``k·sqrt(σa² + σb²)`` (k = 3 by
default), with each result's realistic σ when it has one, else its scaled σ (formal × σ̂0) —
which is optimistic under time-correlated POS errors, and the verdict says so.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import sqlite3
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calib.core import frames
from calib.core.errors import CalibError

ANGLES = ("roll", "pitch", "yaw")
ENV_DB = "MLS_HISTORY_DB"
DEFAULT_K_SIGMA = 3.0
_SCHEMA_VERSION = 1


class HistoryError(CalibError, ValueError):
    """The history database or a record is missing or unusable (the message says which)."""


class ResultFormatError(CalibError, ValueError):
    """A result.json does not follow docs/architecture.md §4 (the message names the field)."""


# -- result.json ----------------------------------------------------------------------------


def _angles(d: dict, key: str, source: str, positive: bool) -> dict[str, float]:
    v = d[key]
    if isinstance(v, (list, tuple)) and len(v) == 3:  # roll, pitch, yaw order
        v = dict(zip(ANGLES, v, strict=False))
    if not isinstance(v, dict):
        raise ResultFormatError(
            f"{source}: {key} is {v!r}, expected an object {{roll, pitch, yaw}} in degrees"
        )
    out = {}
    for a in ANGLES:
        if a not in v:
            raise ResultFormatError(f"{source}: {key}.{a} is missing")
        x = v[a]
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ResultFormatError(f"{source}: {key}.{a} is {x!r}, expected a finite number")
        if positive and x <= 0:
            raise ResultFormatError(f"{source}: {key}.{a} is {x!r}, expected a positive sigma")
        out[a] = float(x)
    return out


def _number(d: dict, key: str, source: str, minimum: float | None = None, integer: bool = False) -> float:
    x = d[key]
    ok = (isinstance(x, int) if integer else isinstance(x, (int, float))) and not isinstance(x, bool)
    if not ok or not math.isfinite(x) or (minimum is not None and x < minimum):
        what = "an integer" if integer else "a finite number"
        if minimum is not None:
            what += f" ≥ {minimum:g}"
        raise ResultFormatError(f"{source}: {key} is {x!r}, expected {what}")
    return x


def validate_result(result: dict, source: str = "result") -> dict:
    """Check the fields of a calibration result (docs/architecture.md §4) that the history uses; returns a
    normalised copy of them (angles as {roll, pitch, yaw} dicts, degrees). Raises
    :class:`ResultFormatError` naming the first missing or bad field."""
    if not isinstance(result, dict):
        raise ResultFormatError(f"{source}: expected a JSON object, got {type(result).__name__}")
    required = (
        "boresight_deg",
        "sigma_deg",
        "sigma_scaled_deg",
        "correlation",
        "sigma0_squared",
        "n_points",
        "software_version",
    )
    for key in required:
        if key not in result:
            raise ResultFormatError(f"{source}: required field {key!r} is missing")
    out: dict[str, Any] = {
        "boresight_deg": _angles(result, "boresight_deg", source, positive=False),
        "sigma_deg": _angles(result, "sigma_deg", source, positive=True),
        "sigma_scaled_deg": _angles(result, "sigma_scaled_deg", source, positive=True),
        "sigma_realistic_deg": None,
    }
    if result.get("sigma_realistic_deg") is not None:
        out["sigma_realistic_deg"] = _angles(result, "sigma_realistic_deg", source, positive=True)
    corr = result["correlation"]
    if not (
        isinstance(corr, list) and len(corr) == 3 and all(isinstance(r, list) and len(r) == 3 for r in corr)
    ):
        raise ResultFormatError(
            f"{source}: correlation is {corr!r}, expected a 3×3 list of lists (roll, pitch, yaw)"
        )
    for i in range(3):
        for j in range(3):
            x = corr[i][j]
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not -1.000001 <= x <= 1.000001:
                raise ResultFormatError(
                    f"{source}: correlation[{i}][{j}] is {x!r}, expected a number in [−1, 1]"
                )
            if i == j and abs(x - 1.0) > 1e-6:
                raise ResultFormatError(f"{source}: correlation[{i}][{i}] is {x!r}, expected 1")
            if abs(x - corr[j][i]) > 1e-6:
                raise ResultFormatError(
                    f"{source}: correlation is not symmetric "
                    f"([{i}][{j}] = {x!r}, [{j}][{i}] = {corr[j][i]!r})"
                )
    out["correlation"] = [[float(x) for x in r] for r in corr]
    out["sigma0_squared"] = float(_number(result, "sigma0_squared", source, minimum=0.0))
    out["n_points"] = int(_number(result, "n_points", source, minimum=0, integer=True))
    sv = result["software_version"]
    if not isinstance(sv, str) or not sv:
        raise ResultFormatError(f"{source}: software_version is {sv!r}, expected a non-empty string")
    out["software_version"] = sv
    return out


def load_result(path) -> dict:
    """Read and validate a result.json (a directory means its ``result.json``)."""
    p = Path(path)
    if p.is_dir():
        p = p / "result.json"
    try:
        result = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ResultFormatError(f"{p}: file not found") from None
    except json.JSONDecodeError as e:
        raise ResultFormatError(f"{p}:{e.lineno}:{e.colno}: not valid JSON ({e.msg})") from None
    validate_result(result, str(p))
    return result


# -- bundle ---------------------------------------------------------------------------------


def _bundle_inputs(bundle: Path) -> list[Path]:
    if not bundle.is_dir():
        raise HistoryError(f"{bundle}: not a bundle directory")
    files = [bundle / "site.yaml"]
    if (bundle / "trajectory.csv").exists():
        files.append(bundle / "trajectory.csv")
    elif (bundle / "trajectory.sbet").exists():
        files.append(bundle / "trajectory.sbet")
        if (bundle / "trajectory.smrmsg").exists():
            files.append(bundle / "trajectory.smrmsg")
    else:
        raise HistoryError(f"{bundle}: no trajectory.csv or trajectory.sbet")
    points = [bundle / n for n in ("points.csv", "points.csv.gz") if (bundle / n).exists()]
    if not points:
        raise HistoryError(f"{bundle}: no points.csv or points.csv.gz")
    files.append(points[0])
    if not files[0].exists():
        raise HistoryError(f"{bundle}: no site.yaml")
    return files


def bundle_fingerprint(bundle_path) -> str:
    """SHA-256 (hex) of the bundle's input files (not truth.json, not outputs)."""
    h = hashlib.sha256()
    for f in _bundle_inputs(Path(bundle_path)):
        h.update(f"{f.name}\0{f.stat().st_size}\0".encode())
        with f.open("rb") as fh:
            while chunk := fh.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def bundle_survey_utc(bundle_path) -> str | None:
    """UTC ISO time of the bundle's first trajectory epoch (trajectory.csv only), else None."""
    p = Path(bundle_path) / "trajectory.csv"
    if not p.exists():
        return None
    with p.open(encoding="utf-8") as fh:
        fh.readline()
        first = fh.readline().split(",", 1)[0]
    try:
        gps_s = float(first)
    except ValueError:
        return None
    return _iso(frames.gps_ns_to_utc(frames.seconds_to_gps_ns(gps_s)))


def _iso(t: _dt.datetime) -> str:
    return t.astimezone(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


# -- database -------------------------------------------------------------------------------


def default_db_path() -> Path:
    env = os.environ.get(ENV_DB)
    if env:
        return Path(env).expanduser()
    data = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data) / "marine-mls" / "history.sqlite"


_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    vessel TEXT NOT NULL,
    mount_id TEXT NOT NULL,
    survey_utc TEXT,
    recorded_utc TEXT NOT NULL,
    software_version TEXT NOT NULL,
    bundle_path TEXT NOT NULL,
    bundle_fingerprint TEXT NOT NULL,
    n_points INTEGER NOT NULL,
    sigma0_squared REAL NOT NULL,
    roll_deg REAL NOT NULL, pitch_deg REAL NOT NULL, yaw_deg REAL NOT NULL,
    sigma_roll_deg REAL NOT NULL, sigma_pitch_deg REAL NOT NULL, sigma_yaw_deg REAL NOT NULL,
    sigma_scaled_roll_deg REAL NOT NULL, sigma_scaled_pitch_deg REAL NOT NULL,
    sigma_scaled_yaw_deg REAL NOT NULL,
    sigma_realistic_roll_deg REAL, sigma_realistic_pitch_deg REAL, sigma_realistic_yaw_deg REAL,
    correlation_json TEXT NOT NULL,
    result_json TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS calibrations_vessel ON calibrations (vessel, mount_id);
CREATE INDEX IF NOT EXISTS calibrations_bundle ON calibrations (bundle_fingerprint);
"""


def _db_path(db) -> Path:
    return Path(db).expanduser() if db is not None else default_db_path()


def _connect(db) -> sqlite3.Connection:
    path = _db_path(db)
    con = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        con = sqlite3.connect(path, timeout=10.0)
        version = con.execute("PRAGMA user_version").fetchone()[0]
        if version > _SCHEMA_VERSION:
            raise HistoryError(
                f"{path}: history schema version {version} is newer than this "
                f"software's ({_SCHEMA_VERSION}); upgrade marine-mls"
            )
        con.executescript(_SCHEMA)
        con.execute(f"PRAGMA user_version = {_SCHEMA_VERSION}")
        return con
    except (sqlite3.DatabaseError, OSError, HistoryError) as e:
        if con is not None:
            con.close()
        if isinstance(e, HistoryError):
            raise
        what = (
            "not a usable history database"
            if isinstance(e, sqlite3.DatabaseError)
            else "cannot open the history database"
        )
        raise HistoryError(f"{path}: {what} ({e})") from None


@dataclass(frozen=True)
class HistoryRecord:
    id: int
    vessel: str
    mount_id: str
    survey_utc: str | None
    recorded_utc: str
    software_version: str
    bundle_path: str
    bundle_fingerprint: str
    n_points: int
    sigma0_squared: float
    result: dict  # the whole result.json as recorded

    @property
    def boresight_deg(self) -> dict[str, float]:
        return validate_result(self.result)["boresight_deg"]

    @property
    def verdict(self) -> str | None:
        """The result's verdict (trusted, questionable, refused); None for an older result."""
        v = self.result.get("verdict")
        return v if isinstance(v, str) else None

    @property
    def date_utc(self) -> str:
        """The survey date when known, else the recording date."""
        return self.survey_utc or self.recorded_utc

    @property
    def label(self) -> str:
        return f"#{self.id} ({self.vessel}/{self.mount_id}, {self.date_utc[:10]})"


def _record(row) -> HistoryRecord:
    return HistoryRecord(
        row[0],
        row[1],
        row[2],
        row[3],
        row[4],
        row[5],
        row[6],
        row[7],
        int(row[8]),
        float(row[9]),
        json.loads(row[10]),
    )


_COLUMNS = (
    "id, vessel, mount_id, survey_utc, recorded_utc, software_version, bundle_path, "
    "bundle_fingerprint, n_points, sigma0_squared, result_json"
)


def record_result(
    result_dict: dict,
    bundle_path,
    vessel: str | None,
    mount_id: str,
    db=None,
    *,
    survey_utc: str | None = None,
) -> int:
    """Record a validated result of the bundle at ``bundle_path``; returns the row id.

    ``vessel=None`` takes the vessel named in the bundle's site.yaml. ``survey_utc`` defaults to
    the bundle's first trajectory epoch. The same result of the same bundle (same fingerprint,
    vessel, mount and result) is recorded once: its existing id is returned.
    """
    norm = validate_result(result_dict, "result")
    if not isinstance(mount_id, str) or not mount_id.strip():
        raise HistoryError(f"mount id {mount_id!r}: expected a non-empty name")
    bundle = Path(bundle_path).resolve()
    fingerprint = bundle_fingerprint(bundle)
    if vessel is None:
        from calib.io.site import load_site

        vessel = load_site(bundle / "site.yaml").vessel
    if not isinstance(vessel, str) or not vessel.strip():
        raise HistoryError(f"vessel {vessel!r}: expected a non-empty name")
    if survey_utc is None:
        survey_utc = bundle_survey_utc(bundle)
    blob = json.dumps(result_dict, sort_keys=True, separators=(",", ":"))
    with closing(_connect(db)) as con, con:
        row = con.execute(
            "SELECT id FROM calibrations WHERE bundle_fingerprint = ? AND vessel = ? AND "
            "mount_id = ? AND result_json = ? ORDER BY id LIMIT 1",
            (fingerprint, vessel, mount_id, blob),
        ).fetchone()
        if row is not None:
            return int(row[0])
        real = norm["sigma_realistic_deg"] or {}
        row = {
            "vessel": vessel,
            "mount_id": mount_id,
            "survey_utc": survey_utc,
            "recorded_utc": _iso(_dt.datetime.now(_dt.UTC)),
            "software_version": norm["software_version"],
            "bundle_path": str(bundle),
            "bundle_fingerprint": fingerprint,
            "n_points": norm["n_points"],
            "sigma0_squared": norm["sigma0_squared"],
            **{f"{a}_deg": norm["boresight_deg"][a] for a in ANGLES},
            **{f"sigma_{a}_deg": norm["sigma_deg"][a] for a in ANGLES},
            **{f"sigma_scaled_{a}_deg": norm["sigma_scaled_deg"][a] for a in ANGLES},
            **{f"sigma_realistic_{a}_deg": real.get(a) for a in ANGLES},
            "correlation_json": json.dumps(norm["correlation"]),
            "result_json": blob,
        }
        cur = con.execute(
            f"INSERT INTO calibrations ({', '.join(row)}) VALUES ({', '.join('?' * len(row))})",
            tuple(row.values()),
        )
        assert cur.lastrowid is not None  # an INSERT sets it
        return int(cur.lastrowid)


def list_results(vessel: str | None = None, db=None, mount_id: str | None = None) -> list[HistoryRecord]:
    """Recorded results, oldest survey first (optionally of one vessel / mount)."""
    where, args = [], []
    if vessel is not None:
        where.append("vessel = ?")
        args.append(vessel)
    if mount_id is not None:
        where.append("mount_id = ?")
        args.append(mount_id)
    sql = f"SELECT {_COLUMNS} FROM calibrations"
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += " ORDER BY COALESCE(survey_utc, recorded_utc), id"
    if not _db_path(db).exists():  # reading does not create a database
        return []
    with closing(_connect(db)) as con:
        return [_record(r) for r in con.execute(sql, args)]


def get_result(record_id: int, db=None) -> HistoryRecord:
    if not _db_path(db).exists():
        raise HistoryError(f"no calibration #{record_id}: no history database at {_db_path(db)}")
    with closing(_connect(db)) as con:
        row = con.execute(f"SELECT {_COLUMNS} FROM calibrations WHERE id = ?", (int(record_id),)).fetchone()
    if row is None:
        raise HistoryError(f"no calibration #{record_id} in the history")
    return _record(row)


def resolve_result(ref: str, db=None, which: str = "result") -> tuple[dict | HistoryRecord, str]:
    """A calibration named by a history id (``12`` or ``#12``) or a result.json path (file or
    directory) → (the result, its label) for :func:`compare`; ``which`` names the argument in
    the error when ``ref`` is neither."""
    p = Path(ref)
    if p.exists():
        return load_result(p), str(p)
    digits = ref.lstrip("#")
    if digits.isdigit():
        rec = get_result(int(digits), db=db)
        return rec, rec.label
    raise HistoryError(f"{which} {ref!r}: neither a result.json path nor a history id")


def records_of_bundle(fingerprint: str, db=None) -> list[HistoryRecord]:
    """Earlier results of the same bundle (e.g. to say "this bundle was calibrated before")."""
    if not _db_path(db).exists():
        return []
    with closing(_connect(db)) as con:
        rows = con.execute(
            f"SELECT {_COLUMNS} FROM calibrations WHERE bundle_fingerprint = ? ORDER BY id", (fingerprint,)
        ).fetchall()
    return [_record(r) for r in rows]


# -- comparison -----------------------------------------------------------------------------


@dataclass(frozen=True)
class AngleChange:
    angle: str
    a_deg: float
    b_deg: float
    difference_deg: float  # b − a
    sigma_a_deg: float
    sigma_b_deg: float
    sigma_combined_deg: float  # sqrt(σa² + σb²)
    n_sigma: float  # |Δ| / σ_combined
    changed: bool  # n_sigma > k


@dataclass(frozen=True)
class Comparison:
    a_label: str
    b_label: str
    angles: tuple[AngleChange, ...]
    k_sigma: float
    sigma_kind_a: str  # "realistic" or "scaled"
    sigma_kind_b: str
    same_bundle: bool | None  # None when a fingerprint is unknown (a bare result.json)
    message: str

    @property
    def changed(self) -> bool:
        return any(a.changed for a in self.angles)

    def angle(self, name: str) -> AngleChange:
        return next(a for a in self.angles if a.angle == name)


def _fmt_deg(x: float) -> str:
    return f"{x:.3f}°" if abs(x) >= 0.01 else f"{x:.4f}°"


def _fmt_sigma(n: float) -> str:
    return f"{n:.0f}σ" if n >= 10 else f"{n:.1f}σ"


def _side(x, name: str) -> tuple[dict, str, str | None]:
    """(normalised result, label, fingerprint) of a HistoryRecord or a result dict."""
    if isinstance(x, HistoryRecord):
        return validate_result(x.result, x.label), x.label, x.bundle_fingerprint
    return validate_result(x, name), name, None


def compare(
    a, b, k_sigma: float = DEFAULT_K_SIGMA, *, a_label: str | None = None, b_label: str | None = None
) -> Comparison:
    """Whether calibration ``b`` differs from ``a`` (each a HistoryRecord or a result dict)."""
    if not (k_sigma > 0):
        raise ValueError(f"k_sigma = {k_sigma!r}: expected a positive number")
    ra, la, fa = _side(a, a_label or "A")
    rb, lb, fb = _side(b, b_label or "B")
    la, lb = a_label or la, b_label or lb
    kinds, sig = [], []
    for r in (ra, rb):
        real = r["sigma_realistic_deg"]
        kinds.append("realistic" if real is not None else "scaled")
        sig.append(real if real is not None else r["sigma_scaled_deg"])
    changes = []
    for ang in ANGLES:
        va, vb = ra["boresight_deg"][ang], rb["boresight_deg"][ang]
        sa, sb = sig[0][ang], sig[1][ang]
        sc = math.hypot(sa, sb)
        n = abs(vb - va) / sc
        changes.append(AngleChange(ang, va, vb, vb - va, sa, sb, sc, n, n > k_sigma))
    moved = [c for c in changes if c.changed]
    if moved:
        what = ", ".join(
            f"{c.angle} changed by {_fmt_deg(c.difference_deg)}, {_fmt_sigma(c.n_sigma)}" for c in moved
        )
        message = f"{what}: the mount has moved; recalibrate after each re-installation"
    else:
        top = max(changes, key=lambda c: c.n_sigma)
        message = f"no angle changed beyond {k_sigma:g}σ (largest: {top.angle} {_fmt_sigma(top.n_sigma)})"
    if "scaled" in kinds:
        message += (
            "; note: scaled σ (no realistic σ in "
            + " and ".join(lbl for lbl, k in zip((la, lb), kinds, strict=False) if k == "scaled")
            + ") is optimistic when POS errors are correlated in time"
        )
    same = None if fa is None or fb is None else fa == fb
    if same:
        message += "; both results come from the same bundle"
    return Comparison(la, lb, tuple(changes), float(k_sigma), kinds[0], kinds[1], same, message)

"""Point-cloud files for the assessment tools: LAS/LAZ (laspy + lazrs) and ASCII.

ASCII clouds: one point per line, ``x y z`` then optional extra columns, separated by spaces,
tabs, commas or semicolons (detected from the first data line). Lines starting with ``#`` are
comments. A header line of column names is recognised when it is the first non-comment line and
is not numeric, or when it starts with ``//`` (CloudCompare's convention), e.g.
``//X Y Z Intensity``. Written ASCII files carry such a ``//`` header.

Per-point results (e.g. C2C distances) are written back with the cloud: into a LAS/LAZ file as
extra-bytes dimensions (float64; an existing dimension of the same name is overwritten), into an
ASCII file as appended columns. A LAS/LAZ input written to LAS/LAZ keeps all its points' fields
and its header (CRS, scales, offsets); an ASCII input written to LAS/LAZ becomes LAS 1.4 point
format 6 with a 0.1 mm scale (coarser only when the cloud spans more than 214 km), its extra
columns extra dimensions (``ascii_<name>`` where the name is a standard LAS dimension).
"""

from __future__ import annotations

import copy
import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calib.core.errors import CalibError

if TYPE_CHECKING:
    import laspy

LAS_SUFFIXES = (".las", ".laz")
_SEPARATORS = (",", ";", "\t")
_INT32_MAX = 2**31 - 1


class CloudError(CalibError, ValueError):
    """A point-cloud file is missing or malformed (the message names file and line)."""


@dataclass
class PointCloud:
    xyz_m: np.ndarray  # (n, 3) float64
    columns: dict[str, np.ndarray] = field(default_factory=dict)  # extra ASCII columns
    path: Path | None = None
    las: laspy.LasData | None = None  # the laspy.LasData read, kept to write it back unchanged
    delimiter: str | None = None  # ASCII separator read (None: whitespace)

    def __len__(self) -> int:
        return self.xyz_m.shape[0]


def is_las(path) -> bool:
    return Path(path).suffix.lower() in LAS_SUFFIXES


def read_cloud(path) -> PointCloud:
    """Read a LAS/LAZ (by suffix) or ASCII cloud; raises :class:`CloudError`."""
    p = Path(path)
    if p.is_dir():
        raise CloudError(f"{p}: is a directory, expected a point-cloud file")
    if not p.is_file():
        raise CloudError(f"{p}: file not found")
    cloud = _read_las(p) if is_las(p) else _read_ascii(p)
    if len(cloud) == 0:
        raise CloudError(f"{p}: no points")
    return cloud


# -- LAS / LAZ ------------------------------------------------------------------------------


def _read_las(p: Path) -> PointCloud:
    import laspy

    try:
        las = laspy.read(p)
    except (laspy.errors.LaspyException, OSError, ValueError) as e:
        raise CloudError(f"{p}: not a readable LAS/LAZ file ({e})") from None
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    return PointCloud(xyz, {}, p, las)


def _las_scale(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.floor(xyz.min(axis=0))
    span = float((xyz.max(axis=0) - offsets).max())
    for scale in (1e-4, 1e-3, 1e-2, 1e-1):
        if span / scale < _INT32_MAX:
            return np.full(3, scale), offsets
    raise CloudError(f"cloud spans {span:.0f} m: too large for a LAS file")


def _new_las(xyz: np.ndarray):
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = _las_scale(xyz)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return las


def _write_las(path: Path, cloud: PointCloud, extra: dict[str, np.ndarray]) -> None:
    import laspy

    if cloud.las is not None:
        src = cloud.las
        las = laspy.LasData(copy.deepcopy(src.header), src.points.copy())
    else:
        las = _new_las(cloud.xyz_m)
        # an ASCII cloud's extra columns become extra dimensions (prefixed where the name is
        # one of the point format's standard dimensions, e.g. "intensity" → "ascii_intensity")
        standard = {n.lower() for n in las.point_format.standard_dimension_names}
        cols = {(f"ascii_{k}" if k.lower() in standard else k)[:32]: v for k, v in cloud.columns.items()}
        extra = {**cols, **extra}
    existing = set(las.point_format.extra_dimension_names)
    new = [
        laspy.ExtraBytesParams(name=name, type=np.float64, description=name[:31])
        for name in extra
        if name not in existing
    ]
    if new:
        las.add_extra_dims(new)
    for name, values in extra.items():
        las[name] = np.asarray(values, dtype=np.float64)
    try:
        las.write(path)
    except (laspy.errors.LaspyException, OSError) as e:
        raise CloudError(f"{path}: could not write ({e})") from None


# -- ASCII ----------------------------------------------------------------------------------


def _split(line: str, delimiter: str | None) -> list[str]:
    return line.split(delimiter) if delimiter else line.split()


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _ascii_header(lines: list[str]) -> tuple[list[str] | None, int | None]:
    """The column names of an ASCII cloud's header (a ``//`` line, or a first line that does not
    start with a number; None: none) and the index of its first data line (None: no data)."""
    names: list[str] | None = None
    for i, raw in enumerate(lines):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith("//"):
            if names is None:
                names = s[2:].replace(",", " ").replace(";", " ").split()
            continue
        if names is None and not _is_number(re.split(r"[\s,;]+", s)[0]):
            names = re.split(r"[\s,;]+", s)
            continue
        return names, i
    return names, None


def _read_ascii(p: Path) -> PointCloud:
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise CloudError(
            f"{p}: not a text file (byte {e.start} is not UTF-8); LAS/LAZ files must end in .las or .laz"
        ) from None
    lines = text.splitlines()
    names, first = _ascii_header(lines)
    if first is None:
        raise CloudError(f"{p}: no points")
    sample = lines[first]
    delimiter = next((d for d in _SEPARATORS if d in sample), None)
    ncol = len(_split(sample.strip(), delimiter))
    if ncol < 3:
        raise CloudError(f"{p}:{first + 1}: {ncol} column(s), expected at least x y z")
    body = "\n".join(lines[first:])
    try:
        a = np.loadtxt(io.StringIO(body), delimiter=delimiter, comments="#", ndmin=2)
    except ValueError:
        a = None
    if a is None or a.shape[1] != ncol or not np.isfinite(a).all():
        _locate_ascii_error(p, lines, first, delimiter, ncol)  # raises, naming the line
        raise CloudError(f"{p}: could not parse as {ncol} columns of finite numbers")
    if names is not None and len(names) != ncol:
        raise CloudError(
            f"{p}: the header names {len(names)} columns ({' '.join(names)}) but the data has {ncol}"
        )
    if names is None:
        names = ["x", "y", "z"] + [f"column_{j + 1}" for j in range(3, ncol)]
    columns = {names[j]: a[:, j].copy() for j in range(3, ncol)}
    return PointCloud(np.ascontiguousarray(a[:, :3]), columns, p, None, delimiter)


def _locate_ascii_error(p: Path, lines: list[str], first: int, delimiter, ncol: int) -> None:
    """Raise a CloudError naming the first bad line (slow path after the fast parse failed)."""
    for i in range(first, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        fields = _split(s, delimiter)
        if len(fields) != ncol:
            raise CloudError(f"{p}:{i + 1}: {len(fields)} columns, expected {ncol} like line {first + 1}")
        for j, f in enumerate(fields):
            try:
                v = float(f)
            except ValueError:
                raise CloudError(f"{p}:{i + 1}: column {j + 1} is {f!r}, expected a number") from None
            if not np.isfinite(v):
                raise CloudError(f"{p}:{i + 1}: column {j + 1} is {f!r}, expected a finite number")


def _write_ascii(path: Path, cloud: PointCloud, extra: dict[str, np.ndarray]) -> None:
    sep = cloud.delimiter or " "
    names = ["x", "y", "z", *cloud.columns, *extra]
    cols = [cloud.xyz_m[:, 0], cloud.xyz_m[:, 1], cloud.xyz_m[:, 2]]
    cols += [np.asarray(c, dtype=float) for c in cloud.columns.values()]
    cols += [np.asarray(c, dtype=float) for c in extra.values()]
    fmt = ["%.6f"] * 3 + ["%.10g"] * len(cloud.columns) + ["%.6f"] * len(extra)
    try:
        np.savetxt(
            path, np.column_stack(cols), fmt=fmt, delimiter=sep, header="//" + sep.join(names), comments=""
        )
    except OSError as e:
        raise CloudError(f"{path}: could not write ({e})") from None


def write_cloud(path, cloud: PointCloud, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Write ``cloud`` with the per-point ``extra`` values (name → (n,) array) to ``path``:
    LAS/LAZ extra dimensions or appended ASCII columns, by the suffix of ``path``."""
    p = Path(path)
    extra = dict(extra or {})
    for name, values in extra.items():
        if np.shape(values) != (len(cloud),):
            raise CloudError(f"{p}: column {name!r} has shape {np.shape(values)}, expected ({len(cloud)},)")
    if is_las(p):
        _write_las(p, cloud, extra)
    else:
        _write_ascii(p, cloud, extra)
    return p

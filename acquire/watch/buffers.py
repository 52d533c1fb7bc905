"""What the mount watch keeps of the record stream: the navigation and a decimated share of the
profiler's returns, from the start of the oldest line it still needs (nothing older).

- :class:`NavBuffer`: the INS epochs as float64 rows (GPS s, geodetic position, attitude, σ),
  appended per record, consolidated into arrays every :data:`NAV_CHUNK` epochs;
- :class:`PointBuffer`: per profile, the returns inside the watch's range window thinned to a
  budget of ``max_points_per_s`` by a token bucket (numpy per profile, never per point), held as
  (GPS s, range, scan angle) arrays; past ``max_points`` the stored returns are halved and the
  budget with them, until the buffer empties again — so a block's memory is bounded whatever the
  profiler's rate or the lines' length.

Both are trimmed from the front (:meth:`trim_before`) as lines are used or dropped.
"""

from __future__ import annotations

import math

import numpy as np

from calib.core import frames

NAV_CHUNK = 512
POINT_CHUNK = 256  # profiles per consolidated chunk
#: nav row columns: GPS s, lat, lon, h, roll, pitch, heading (rad), σ n, e, d (m), σ r, p, h (rad)
NAV_COLUMNS = 13
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0  # the phase step of the kept returns between profiles


class NavBuffer:
    """The INS epochs kept (module docstring)."""

    def __init__(self) -> None:
        self._chunks: list[np.ndarray] = []
        self._rows: list[tuple] = []
        self.t_last = -math.inf

    def __len__(self) -> int:
        return sum(c.shape[0] for c in self._chunks) + len(self._rows)

    def add(self, row: tuple) -> bool:
        """One epoch (:data:`NAV_COLUMNS` values, time first); False when not after the last."""
        if not row[0] > self.t_last:
            return False
        self.t_last = row[0]
        self._rows.append(row)
        if len(self._rows) >= NAV_CHUNK:
            self._consolidate()
        return True

    def _consolidate(self) -> None:
        if self._rows:
            self._chunks.append(np.array(self._rows, dtype=float))
            self._rows = []

    def snapshot(self) -> list[np.ndarray]:
        """The arrays held now (never modified afterwards: trimming makes new ones), for
        :func:`nav_rows` in another thread."""
        self._consolidate()
        return list(self._chunks)

    def trim_before(self, t: float) -> None:
        self._consolidate()
        keep = []
        for c in self._chunks:
            if c[-1, 0] < t:
                continue
            keep.append(c[np.searchsorted(c[:, 0], t) :] if c[0, 0] < t else c)
        self._chunks = keep


class PointBuffer:
    """The returns kept for the watch (module docstring)."""

    def __init__(
        self,
        max_points_per_s: float,
        min_range_m: float,
        max_range_m: float,
        max_points: int = 4_000_000,
    ) -> None:
        self.budget = float(max_points_per_s)
        self.min_range_m, self.max_range_m = float(min_range_m), float(max_range_m)
        self.max_points = int(max_points)
        self.scale = 1.0  # the budget's share in force (halved each time the buffer overflows)
        self._allow = 0.0
        self._phase = 0.0
        self._t_prev: float | None = None
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._n = 0
        self.seen = 0  # returns offered
        self.kept = 0  # returns kept
        self.halvings = 0

    def __len__(self) -> int:
        return self._n

    def add(self, gps_ns: np.ndarray, range_m: np.ndarray, scan_angle_rad: np.ndarray) -> int:
        """One profile's returns (per-point GPS ns, range, angle; NaN range = no return);
        returns how many were kept."""
        n = range_m.shape[0]
        if n == 0 or gps_ns.shape[0] != n or scan_angle_rad.shape[0] != n:
            return 0
        self.seen += n
        t_end = float(gps_ns[-1]) * 1e-9
        rate = self.budget * self.scale
        if self._t_prev is None or not 0.0 <= t_end - self._t_prev <= 1.0:
            dt = 0.005  # the first profile (or after a gap): one profile at 200 Hz
        else:
            dt = t_end - self._t_prev
        self._t_prev = t_end
        self._allow = min(self._allow + rate * dt, max(rate * 0.1, 1.0))
        k_max = int(self._allow)
        if k_max <= 0:
            return 0
        with np.errstate(invalid="ignore"):
            valid = np.flatnonzero((range_m >= self.min_range_m) & (range_m <= self.max_range_m))
        m = valid.size
        if m == 0:
            return 0
        k = min(k_max, m)
        step = m / k
        self._phase = (self._phase + GOLDEN) % 1.0  # a different comb of the returns each profile
        idx = valid[np.minimum(((np.arange(k) + self._phase) * step).astype(np.int64), m - 1)]
        self._allow -= k
        self._parts.append(
            (
                frames.gps_ns_to_seconds(gps_ns[idx]),
                range_m[idx].astype(np.float32),
                scan_angle_rad[idx].astype(np.float32),
            )
        )
        self._n += k
        self.kept += k
        if len(self._parts) >= POINT_CHUNK:
            self._consolidate()
        if self._n > self.max_points:
            self._halve()
        return k

    def _consolidate(self) -> None:
        if self._parts:
            t, r, a = zip(*self._parts, strict=True)
            self._chunks.append((np.concatenate(t), np.concatenate(r), np.concatenate(a)))
            self._parts = []

    def _halve(self) -> None:
        self._consolidate()
        self._chunks = [(t[::2], r[::2], a[::2]) for t, r, a in self._chunks]
        self._n = sum(c[0].shape[0] for c in self._chunks)
        self.scale *= 0.5
        self.halvings += 1

    def snapshot(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The arrays held now (never modified afterwards), for :func:`select_points` in
        another thread."""
        self._consolidate()
        return list(self._chunks)

    def trim_before(self, t: float) -> None:
        self._consolidate()
        keep: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for c in self._chunks:  # a chunk is in time order (profiles as they came): its ends decide
            if c[0][0] >= t:
                keep.append(c)
            elif c[0][-1] >= t:
                sel = c[0] >= t
                keep.append((c[0][sel], c[1][sel], c[2][sel]))
        self._chunks = keep
        self._n = sum(c[0].shape[0] for c in keep)
        if self._n < self.max_points // 4 and self.scale < 1.0:  # room again: the full budget
            self.scale = min(1.0, self.scale * 2.0)


def nav_rows(chunks: list[np.ndarray], t0: float = -math.inf, t1: float = math.inf) -> np.ndarray:
    """The epochs of a :meth:`NavBuffer.snapshot` with t0 ≤ t ≤ t1, as an (n, 13) array."""
    if not chunks:
        return np.empty((0, NAV_COLUMNS))
    a = np.concatenate(chunks)
    t = a[:, 0]
    return a[np.searchsorted(t, t0, "left") : np.searchsorted(t, t1, "right")]


def select_points(chunks: list[tuple], windows: list[tuple[int, float, float]]):
    """The returns of a :meth:`PointBuffer.snapshot` inside each ``(line id, t0, t1)`` window:
    (line ids, GPS s, range, angle) float64 arrays, time-ordered within each line."""
    if chunks:
        t, r, a = (np.concatenate(x) for x in zip(*chunks, strict=True))
    else:
        t = r = a = np.empty(0)
    out: list[tuple] = []
    for lid, t0, t1 in windows:
        sel = np.flatnonzero((t >= t0) & (t <= t1))
        sel = sel[np.argsort(t[sel], kind="stable")]
        out.append((np.full(sel.size, lid, np.int64), t[sel], r[sel].astype(float), a[sel].astype(float)))
    if not out:
        return np.empty(0, np.int64), np.empty(0), np.empty(0), np.empty(0)
    ids, tt, rr, aa = (np.concatenate(x) for x in zip(*out, strict=True))
    return ids, tt, rr, aa

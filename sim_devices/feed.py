"""The scenario as the devices see it: a window of a :func:`calib.sim.simulate.simulate` result cut
into INS epochs, profiler profiles and pass markers (pure numpy, no I/O).

- :class:`InsTrack` — the INS epochs on the GPS-time grid of the output rate (multiples of
  1/rate from the GPS epoch): the **observed** trajectory (the POS solution, with its errors and
  sigmas) interpolated at each epoch (gaps between passes of a scenario without turns are
  bridged: the INS reports a straight transit), velocity from the true trajectory (central
  difference over ±20 ms), heave = down position minus its mean, surge and sway 0.
- :class:`ProfileGrid` — every profile the profiler sends in the window, and the scenario's
  returns placed in them. The simulator fires each pass's profiles from that pass's own start
  time, at ``effective_profile_rate_hz`` with ``effective_points_per_360`` points evenly spaced
  in time and angle; it returns only the hits. The grid is **derived from that output**: in a
  pass, every return sits at ``t_first + j·dt`` (j from its time) and at encoder slot
  ``round(α/Δα)`` (from its reported angle, whose noise is far below Δα/2), so
  ``(slot − j) mod K`` is one constant — the slot of the pass's first return — which places the
  pass's profile boundaries (slot 0 = scan angle 0). Profiles run back to back on that grid
  from the start of the window until the next pass's grid begins: there the stream pauses for
  less than one profile period (the grid re-phases; the profile counter stays continuous).
  Profiles without returns are sent too (ranges 0 = no return), as a running scanner does; only
  the scenario's recorded angular windows are sent (:attr:`ProfileGrid.runs`).
- :class:`PassMark` — pass start/end at each pass's line start/end (the CAN event markers).

The feed can be moved in time by whole seconds (``time_shift``, e.g. to *now*: real devices
send today's date, and a daemon dates time-of-day tags before the first ZDA from the host's
date); every GPS time in it is then scenario time + ``time_shift_ns``.

Quantization on the wire (what a decoder can give back): range 0.1 mm, intensity 1/65535 (the
scenario's 0–1 intensity × 65535), point time and scan angle from each ZFP1 packet's integer
``t0_ns``/``dt_ns`` and ``angle0_udeg``/``dangle_udeg`` (each packet's first point is rounded
exactly; the step is rounded to 1 ns and 1 µdeg, so the error grows along a packet by at most
½ ns and ½ µdeg per point). ZFP1 carries no per-point angle, so the scenario's scan-angle noise
(``noise.scanner.sigma_scan_angle_deg``) does not reach the wire: the angles sent are the encoder
grid's.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from calib.core.frames import utc_to_gps_ns, wrap_2pi
from calib.io.bundle import ScanPoints
from drivers.hydrins.nav import NavRecord
from sim_devices.errors import SimDevicesError

if TYPE_CHECKING:
    from calib.sim.result import SimResult

NS_PER_S = 1_000_000_000
RANGE_UNIT_M = 1e-4
INTENSITY_FULL_SCALE = 65535
SIGMA_VELOCITY_M_S = 0.01  # the INS velocity σ reported (the scenario has none)
_VELOCITY_HALF_STEP_S = 0.02


class FeedError(SimDevicesError, ValueError):
    """The scenario cannot be turned into device streams as asked (the message says why)."""


def seconds_to_ns(t_s) -> np.ndarray:
    """Float GPS seconds → int64 ns, without the 256-ns loss of ``t·1e9`` at 1e9 s."""
    t = np.asarray(t_s, dtype=np.float64)
    sec = np.floor(t)
    return sec.astype(np.int64) * NS_PER_S + np.rint((t - sec) * 1e9).astype(np.int64)


# -- INS ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InsTrack:
    period_ns: int
    gps_ns: np.ndarray  # (n,) int64 epoch times
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray  # ellipsoidal
    rpy_rad: np.ndarray  # (n, 3) canonical roll, pitch, heading
    v_ned_m_s: np.ndarray  # (n, 3)
    heave_m: np.ndarray  # + down
    sigma_p_m: np.ndarray  # (n, 3) north, east, down (NaN when the scenario has none)
    sigma_rpy_rad: np.ndarray  # (n, 3)

    def __len__(self) -> int:
        return int(self.gps_ns.shape[0])

    def nav(self, k: int, source: str = "nmea") -> NavRecord:
        """Epoch ``k`` as a canonical NavRecord (status words are the emulator's to set)."""
        r, p, h = self.rpy_rad[k]
        vn, ve, vd = self.v_ned_m_s[k]
        sn, se, sd = self.sigma_p_m[k]
        sr, sp, sh = self.sigma_rpy_rad[k]
        return NavRecord(
            source,
            gps_ns=int(self.gps_ns[k]),
            lat_deg=float(self.lat_deg[k]),
            lon_deg=float(self.lon_deg[k]),
            height_m=float(self.height_m[k]),
            height_ref="ellipsoid",
            roll_rad=float(r),
            pitch_rad=float(p),
            heading_rad=float(h),
            v_north_m_s=float(vn),
            v_east_m_s=float(ve),
            v_down_m_s=float(vd),
            surge_m=0.0,
            sway_m=0.0,
            heave_m=float(self.heave_m[k]),
            sigma_roll_rad=float(sr),
            sigma_pitch_rad=float(sp),
            sigma_heading_rad=float(sh),
            sigma_north_m=float(sn),
            sigma_east_m=float(se),
            sigma_down_m=float(sd),
            sigma_v_north_m_s=SIGMA_VELOCITY_M_S,
            sigma_v_east_m_s=SIGMA_VELOCITY_M_S,
            sigma_v_down_m_s=SIGMA_VELOCITY_M_S,
        )


def ins_track(sim, start_ns: int, end_ns: int, rate_hz: float) -> InsTrack:
    """The INS epochs of [start_ns, end_ns) at ``rate_hz`` (see the module docstring)."""
    period = NS_PER_S / rate_hz
    if not (rate_hz > 0 and period == int(period)):
        raise FeedError(
            f"INS rate {rate_hz:g} Hz: expected a rate whose period is a whole number "
            f"of nanoseconds (1, 2, 5, 10, 20, 25, 50, 100, 125, 200 Hz ...)"
        )
    period = int(period)
    first = -(-start_ns // period) * period
    gps = np.arange(first, end_ns, period, dtype=np.int64)
    if gps.size == 0:
        raise FeedError(f"the run window is shorter than one INS period ({period / 1e6:g} ms)")
    obs = replace(sim.trajectory_observed, max_gap_s=math.inf)
    true = replace(sim.trajectory_true, max_gap_s=math.inf)
    t = gps.astype(np.float64) / 1e9
    poses = obs.interpolate(t)
    lat, lon, h = obs.frame.to_geodetic(poses.p_lgf_m)
    t_lo, t_hi = true.t_gps_s[0], true.t_gps_s[-1]
    tp = np.minimum(t + _VELOCITY_HALF_STEP_S, t_hi)
    tm = np.maximum(t - _VELOCITY_HALF_STEP_S, t_lo)
    v = (true.interpolate(tp).p_lgf_m - true.interpolate(tm).p_lgf_m) / (tp - tm)[:, None]
    heave = poses.p_lgf_m[:, 2] - float(np.mean(obs.p_lgf_m[:, 2]))
    nan3 = np.full((gps.size, 3), np.nan)
    return InsTrack(
        period,
        gps,
        np.asarray(lat, float),
        np.asarray(lon, float),
        np.asarray(h, float),
        poses.rpy_rad,
        v,
        heave,
        nan3 if poses.sigma_p_m is None else poses.sigma_p_m,
        nan3 if poses.sigma_rpy_rad is None else poses.sigma_rpy_rad,
    )


# -- profiler -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ProfileGrid:
    profile_rate_hz: float
    points_per_360: int
    start_ns: np.ndarray  # (P,) int64: GPS ns of slot 0 (scan angle 0) of each profile
    runs: tuple[tuple[int, int], ...]  # recorded slots [first, end), in time order
    ret_offsets: np.ndarray  # (P+1,): the returns of profile p are ret_*[off[p]:off[p+1]]
    ret_slot: np.ndarray  # (N,) int64, sorted within each profile
    ret_range_01mm: np.ndarray  # (N,) uint32
    ret_intensity: np.ndarray  # (N,) uint16
    ret_point: np.ndarray  # (N,) index into the simulation's ScanPoints
    returns_outside: int = 0  # returns timed inside the window but in a profile cut by its edges

    @property
    def dt_ns(self) -> float:
        """Point period (ns, not an integer in general)."""
        return NS_PER_S / (self.profile_rate_hz * self.points_per_360)

    @property
    def dangle_udeg(self) -> float:
        return 360e6 / self.points_per_360

    @property
    def period_ns(self) -> float:
        return NS_PER_S / self.profile_rate_hz

    def __len__(self) -> int:
        return int(self.start_ns.shape[0])

    def point_gps_ns(self, profile: int, slot) -> np.ndarray | int:
        """True GPS ns of slot(s) of a profile."""
        s = np.asarray(slot)
        out = self.start_ns[profile] + np.rint(s * self.dt_ns).astype(np.int64)
        return int(out) if out.ndim == 0 else out

    def profile_returns(self, profile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, b = self.ret_offsets[profile], self.ret_offsets[profile + 1]
        return self.ret_slot[a:b], self.ret_range_01mm[a:b], self.ret_intensity[a:b]


def _runs(mask: np.ndarray) -> tuple[tuple[int, int], ...]:
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return tuple((int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True))


def _pass_grid(t_s: np.ndarray, angle_rad: np.ndarray, K: int, dt_s: float, pass_id: int):
    """(origin_ns, g): the GPS ns of slot 0 of the pass's first profile, and each return's slot
    index counted from it (profile = g // K, slot = g % K)."""
    rel = (t_s - t_s[0]) / dt_s
    j = np.rint(rel).astype(np.int64)
    off = float(np.max(np.abs(rel - j)))
    if off > 0.25:
        raise FeedError(
            f"pass {pass_id}: return times are not on the profiler's point grid "
            f"(a point period of {dt_s * 1e9:.1f} ns; off by {off:.2f} of it)"
        )
    slot_a = np.rint(wrap_2pi(angle_rad) / (2.0 * np.pi / K)).astype(np.int64) % K
    values, counts = np.unique((slot_a - j) % K, return_counts=True)
    phase = int(values[np.argmax(counts)])
    if counts.max() < 0.9 * j.size:
        raise FeedError(
            f"pass {pass_id}: only {counts.max() / j.size:.0%} of the scan angles sit "
            f"on the encoder grid their times imply (scan-angle noise too large for "
            f"a step of {360.0 / K:.4f}°?)"
        )
    origin_ns = int(seconds_to_ns(t_s[0])) - round(phase * dt_s * 1e9)
    return origin_ns, j + phase


def profile_grid(points: ScanPoints, scanner, start_ns: int, end_ns: int) -> ProfileGrid:
    """Profiles fully inside [start_ns, end_ns) with the returns they hold (module docstring).

    ``scanner`` is the scenario's :class:`calib.sim.scenario.ScannerModel`.
    """
    rate = float(scanner.effective_profile_rate_hz)
    K = int(scanner.effective_points_per_360)
    dt_s = 1.0 / (rate * K)
    period_ns = NS_PER_S / rate
    mask = scanner.window_mask()
    grids = []  # (origin_ns, pass point indices, g)
    for pid in np.unique(points.pass_id):
        idx = np.flatnonzero(points.pass_id == pid)
        idx = idx[np.argsort(points.t_gps_s[idx], kind="stable")]
        origin, g = _pass_grid(points.t_gps_s[idx], points.scan_angle_rad[idx], K, dt_s, int(pid))
        grids.append((origin, idx, g))
    grids.sort(key=lambda x: x[0])
    if not grids:
        grids = [(start_ns, np.zeros(0, np.int64), np.zeros(0, np.int64))]
    starts = []
    ret_prof, ret_slot, ret_idx = [], [], []
    n_total = 0
    for i, (origin, idx, g) in enumerate(grids):
        seg0 = max(start_ns, origin) if i else start_ns
        seg1 = min(end_ns, grids[i + 1][0]) if i + 1 < len(grids) else end_ns
        n_first = math.ceil((seg0 - origin) / period_ns) - 1
        n_last = math.floor((seg1 - origin) / period_ns) + 1
        n = np.arange(n_first, n_last + 1, dtype=np.int64)
        s = origin + np.rint(n * period_ns).astype(np.int64)
        ok = (s >= seg0) & ((seg1 - s) >= period_ns)  # int differences: exact in float64
        n, s = n[ok], s[ok]
        starts.append(s)
        if idx.size:
            local = g // K
            if n.size:
                inside = (local >= n[0]) & (local <= n[-1])
                ret_prof.append(n_total + local[inside] - n[0])
                ret_slot.append(g[inside] % K)
                ret_idx.append(idx[inside])
        n_total += n.size
    start_arr = np.concatenate(starts) if starts else np.zeros(0, np.int64)
    rp = np.concatenate(ret_prof) if ret_prof else np.zeros(0, np.int64)
    rs = np.concatenate(ret_slot) if ret_slot else np.zeros(0, np.int64)
    ri = np.concatenate(ret_idx) if ret_idx else np.zeros(0, np.int64)
    if rs.size and not mask[rs].all():
        raise FeedError(f"{int((~mask[rs]).sum())} returns lie outside the scanner's angular windows")
    order = np.lexsort((rs, rp))
    rp, rs, ri = rp[order], rs[order], ri[order]
    if rp.size and np.any((np.diff(rp) == 0) & (np.diff(rs) == 0)):
        raise FeedError("two returns fall on one profile slot: the returns are not one profile grid")
    rng = points.range_m[ri]
    if np.any(~(rng > 0)):
        raise FeedError("a return with a range ≤ 0 cannot be sent (0 means no return)")
    r01 = np.maximum(np.rint(rng / RANGE_UNIT_M), 1).astype(np.uint32)
    inten = np.rint(np.clip(points.intensity[ri], 0.0, 1.0) * INTENSITY_FULL_SCALE).astype(np.uint16)
    offsets = np.searchsorted(rp, np.arange(start_arr.size + 1))
    t_ns = seconds_to_ns(points.t_gps_s)
    outside = int(np.count_nonzero((t_ns >= start_ns) & (t_ns < end_ns))) - int(ri.size)
    return ProfileGrid(rate, K, start_arr, _runs(mask), offsets, rs, r01, inten, ri, max(outside, 0))


# -- pass markers -------------------------------------------------------------------------------


@dataclass(frozen=True)
class PassMark:
    gps_ns: int
    kind: str  # pass_start | pass_end
    pass_id: int


def pass_marks(sim, start_ns: int, end_ns: int) -> tuple[PassMark, ...]:
    out = []
    for p in sim.truth["passes"]:
        a, b = (int(x) for x in seconds_to_ns(p["line_gps_s"]))
        out += [PassMark(a, "pass_start", int(p["id"])), PassMark(b, "pass_end", int(p["id"]))]
    return tuple(sorted((m for m in out if start_ns <= m.gps_ns < end_ns), key=lambda m: m.gps_ns))


# -- the feed -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScenarioFeed:
    """One run window of a simulation, on the devices' GPS time scale: device time = scenario
    time + ``time_shift_ns`` (whole seconds; 0 keeps the scenario's own date)."""

    sim: SimResult
    start_gps_ns: int
    end_gps_ns: int
    ins: InsTrack
    grid: ProfileGrid
    marks: tuple[PassMark, ...]
    time_shift_ns: int = 0

    @property
    def duration_s(self) -> float:
        return (self.end_gps_ns - self.start_gps_ns) / NS_PER_S

    @property
    def name(self) -> str:
        return self.sim.scenario.name


def shift_to_now(start_gps_ns: int, now_utc: _dt.datetime | None = None) -> int:
    """The whole seconds that move a window starting at ``start_gps_ns`` to the next GPS second
    after now: devices then send today's date and time (as real ones do), which a daemon dating
    time-of-day tags from the host's date needs."""
    now = utc_to_gps_ns(now_utc or _dt.datetime.now(_dt.UTC))
    return -(-(now - start_gps_ns) // NS_PER_S) * NS_PER_S


def run_window(sim, start: str | float | None = None, duration_s: float | None = None) -> tuple[int, int]:
    """[start, end) GPS ns of a run: ``start`` in seconds after the trajectory's first epoch, or
    ``'pass:N'`` (the line start of pass N); ``duration_s`` None runs to the trajectory's end."""
    t = sim.trajectory_true.t_gps_s
    t0_ns, t1_ns = (int(x) for x in seconds_to_ns([t[0], t[-1]]))
    if start is None:
        start_ns = t0_ns
    elif isinstance(start, str) and start.startswith("pass:"):
        ids = {int(p["id"]): p for p in sim.truth["passes"]}
        try:
            pid = int(start[5:])
            start_ns = int(seconds_to_ns(ids[pid]["line_gps_s"][0]))
        except (ValueError, KeyError):
            raise FeedError(f"start {start!r}: expected pass:N with N one of {sorted(ids)}") from None
    else:
        try:
            s = float(start)
        except ValueError:
            raise FeedError(f"start {start!r}: expected seconds after the scenario start or pass:N") from None
        if not 0 <= s < (t1_ns - t0_ns) / NS_PER_S:
            raise FeedError(
                f"start {s:g} s: expected 0 ≤ start < {(t1_ns - t0_ns) / NS_PER_S:g} s "
                f"(the scenario's trajectory)"
            )
        start_ns = t0_ns + round(s * NS_PER_S)
    if duration_s is None:
        end_ns = t1_ns
    else:
        if not duration_s > 0:
            raise FeedError(f"duration {duration_s:g} s: expected > 0")
        end_ns = start_ns + round(duration_s * NS_PER_S)
        if end_ns > t1_ns:
            raise FeedError(
                f"duration {duration_s:g} s from {(start_ns - t0_ns) / NS_PER_S:g} s runs "
                f"past the scenario's end ({(t1_ns - t0_ns) / NS_PER_S:g} s)"
            )
    return start_ns, end_ns


def make_feed(
    sim,
    start: str | float | None = None,
    duration_s: float | None = None,
    ins_rate_hz: float = 100.0,
    time_shift: int | str = 0,
) -> ScenarioFeed:
    """Cut a simulation into the device streams of one run window; ``time_shift`` (ns, whole
    seconds) moves it in time, ``"now"`` to the present (:func:`shift_to_now`)."""
    a, b = run_window(sim, start, duration_s)
    if time_shift == "now":
        time_shift = shift_to_now(a)
    if not isinstance(time_shift, int) or time_shift % NS_PER_S:
        raise FeedError(f"time shift {time_shift!r}: expected 'now' or whole seconds in ns")
    ins = ins_track(sim, a, b, ins_rate_hz)
    grid = profile_grid(sim.points, sim.scenario.scanner, a, b)
    sh = time_shift
    return ScenarioFeed(
        sim,
        a + sh,
        b + sh,
        replace(ins, gps_ns=ins.gps_ns + sh),
        replace(grid, start_ns=grid.start_ns + sh),
        tuple(replace(m, gps_ns=m.gps_ns + sh) for m in pass_marks(sim, a, b)),
        sh,
    )

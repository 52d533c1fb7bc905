"""Comparisons of decoded records with the scenario truth, within each protocol's quantization
(not a test module)."""

from __future__ import annotations

import math

import numpy as np

from sim_devices.feed import InsTrack, ProfileGrid, seconds_to_ns
from sim_devices.profiler import packet_layout

F32 = 2.0**-24  # float32 relative resolution (half an ulp)


def _close(got: float, want: float, tol: float, what: str) -> None:
    assert abs(got - want) <= tol, f"{what}: got {got!r}, want {want!r} (tolerance {tol:g})"


def _angle(got_rad: float, want_rad: float, tol_rad: float, what: str) -> None:
    d = math.remainder(got_rad - want_rad, 2 * math.pi)
    assert abs(d) <= tol_rad, f"{what}: got {math.degrees(got_rad)!r}°, want {math.degrees(want_rad)!r}°"


def assert_nav_matches(nav, track: InsTrack, k: int, protocol: str) -> None:
    """One decoded NavRecord against epoch k of the track (the emulator's content, without faults)."""
    assert nav.gps_ns == int(track.gps_ns[k])
    r, p, h = (float(x) for x in track.rpy_rad[k])
    vn, ve, vd = (float(x) for x in track.v_ned_m_s[k])
    if protocol == "nmea":  # fixed decimals on the wire: half a last digit
        deg, pos, hgt, vel = math.radians(0.0005), 0.5e-8, 0.0005, 0.0005
        sig_att, sig_pos = math.radians(0.0005), 0.005
    else:  # STDBIN: float32 attitude/speeds/altitude, float64 latitude/longitude
        deg, pos, hgt, vel = math.radians(360.0) * F32, 1e-12, 30.0 * F32, 10.0 * F32
        sig_att, sig_pos = 1e-9, 1e-7
    _angle(nav.roll_rad, r, deg, "roll")
    _angle(nav.pitch_rad, p, deg, "pitch")
    _angle(nav.heading_rad, h, deg, "heading")
    _close(nav.lat_deg, float(track.lat_deg[k]), pos, "lat")
    _close(nav.lon_deg, float(track.lon_deg[k]), pos, "lon")
    _close(nav.height_m, float(track.height_m[k]), hgt, "height")
    _close(nav.v_north_m_s, vn, vel, "v_north")
    _close(nav.v_east_m_s, ve, vel, "v_east")
    _close(nav.v_down_m_s, vd, vel, "v_down")
    _close(nav.heave_m, float(track.heave_m[k]), hgt if protocol == "nmea" else 1e-6, "heave")
    for got, want, name in zip(
        (nav.sigma_roll_rad, nav.sigma_pitch_rad, nav.sigma_heading_rad),
        track.sigma_rpy_rad[k],
        ("σ roll", "σ pitch", "σ heading"),
    ):
        _close(got, float(want), sig_att, name)
    for got, want, name in zip(
        (nav.sigma_north_m, nav.sigma_east_m, nav.sigma_down_m),
        track.sigma_p_m[k],
        ("σ north", "σ east", "σ down"),
    ):
        _close(got, float(want), sig_pos, name)


def serial_emissions(chunks: list, heads: tuple[bytes, ...]) -> list[tuple[bytes, int, int]]:
    """Where each emission of a serial stream arrived: ``(head, chunk, leader)`` for every
    emission in stream order, an emission being what starts with one of ``heads`` (e.g.
    ``b"$HEHDT,"`` for an NMEA epoch block, ``b"$GPZDA,"``) up to the next one; ``chunk`` indexes
    the ``(host_ns, bytes)`` chunk that brought its first byte and ``leader`` the emission whose
    byte starts that chunk (itself, or an earlier one).

    A chunk is stamped when its first bytes are ready, before the read (:mod:`drivers.transport`):
    the stamp is no earlier than the sending of the ``leader``'s bytes, but a reader thread
    descheduled between the stamp and the read (a loaded machine) also takes in what was sent
    meanwhile, and those later emissions carry the same earlier stamp."""
    stream = b"".join(data for _, data in chunks)
    starts = sorted((i, h) for h in heads for i in _positions(stream, h))
    pos = np.array([p for p, _ in starts], dtype=np.int64)
    chunk_end = np.cumsum([len(data) for _, data in chunks])
    chunk_start = chunk_end - [len(data) for _, data in chunks]
    out = []
    for p, head in starts:
        c = int(np.searchsorted(chunk_end, p, side="right"))
        leader = int(np.searchsorted(pos, chunk_start[c], side="right")) - 1
        assert leader >= 0, f"chunk {c} starts before the first emission"
        out.append((head, c, leader))
    return out


def _positions(stream: bytes, head: bytes) -> list[int]:
    out, i = [], stream.find(head)
    while i >= 0:
        out.append(i)
        i = stream.find(head, i + 1)
    return out


def profile_bounds(grid: ProfileGrid, max_payload: int = 1400) -> tuple[int, float]:
    """(time bound ns, angle bound rad) of ZFP1's integer t0/dt and angle0/dangle along a packet."""
    n = max(n for _, n in packet_layout(grid.runs, max_payload))
    t = 1 + n * abs(round(grid.dt_ns) - grid.dt_ns)
    a_udeg = 1 + n * abs(round(grid.dangle_udeg) - grid.dangle_udeg)
    return math.ceil(t), math.radians(a_udeg * 1e-6)


def assert_profile_matches(
    profile, grid: ProfileGrid, points, time_shift_ns: int, clock_error_ns: int = 0
) -> int:
    """A decoded Profile against the grid (every recorded slot, ranges 0 but at the returns) and
    its returns against the simulator's ScanPoints (device time = scenario time + ``time_shift_ns``);
    returns the number of returns checked."""
    p = profile.profile_counter
    K = grid.points_per_360
    t_tol, a_tol = profile_bounds(grid)
    slots = np.rint(profile.scan_angle_rad / (2 * np.pi / K)).astype(np.int64)
    expected_slots = np.concatenate([np.arange(a, b) for a, b in grid.runs])
    assert np.array_equal(slots, expected_slots), f"profile {p}: slots differ from the recorded runs"
    assert np.all(np.abs(profile.scan_angle_rad - slots * (2 * np.pi / K)) <= a_tol)
    want_t = grid.point_gps_ns(p, slots) + clock_error_ns
    assert np.all(np.abs(profile.gps_ns - want_t) <= t_tol), f"profile {p}: point times off the grid"
    r_slots, r01, i16 = grid.profile_returns(p)
    hit = np.isfinite(profile.range_m)
    assert np.array_equal(slots[hit], r_slots), f"profile {p}: returns at the wrong slots"
    assert np.array_equal(np.rint(profile.range_m[hit] / 1e-4).astype(np.uint32), r01)
    assert np.array_equal(profile.intensity[hit], i16)
    assert np.all(profile.intensity[~hit] == 0)
    # against the simulation's own observations (the truth of the scanner)
    a, b = grid.ret_offsets[p], grid.ret_offsets[p + 1]
    idx = grid.ret_point[a:b]
    assert np.all(np.abs(profile.range_m[hit] - points.range_m[idx]) <= 0.5e-4 + 1e-9)
    assert np.all(np.abs(profile.intensity[hit] / 65535.0 - points.intensity[idx]) <= 0.5 / 65535 + 1e-6)
    d = np.remainder(profile.scan_angle_rad[hit] - points.scan_angle_rad[idx] + np.pi, 2 * np.pi) - np.pi
    assert np.all(np.abs(d) <= a_tol + 1e-12)
    # float64 GPS seconds near 1.2e9 resolve 0.24 µs: the simulator's times carry that rounding
    t_sim = seconds_to_ns(points.t_gps_s[idx])
    assert np.all(np.abs(profile.gps_ns[hit] - clock_error_ns - time_shift_ns - t_sim) <= t_tol + 500)
    return int(idx.size)

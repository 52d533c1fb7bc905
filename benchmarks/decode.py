"""Decoder throughput: NMEA sentences/s (vs pynmeagps), STDBIN frames/s, ZFP1 points/s.

Each figure is printed with its ratio to a peer measured in the same run on the same bytes:
- NMEA: pynmeagps (``NMEAReader.parse`` with checksum validation) on the same PHINS-block lines;
- STDBIN: a straightforward decoder written here (one ``struct.unpack_from`` per block, the way
  the iXblue C++ decoder walks the masks) on the real V3 frames;
- ZFP1: a pure-Python decoder written here (``struct.iter_unpack`` over the points) on the same
  datagrams.
Goals: NMEA ≥ 50 k sentences/s, STDBIN ≥ 20 k frames/s, ZFP1 ≥ 20 M points/s, one core.

Run: ``.venv/bin/python benchmarks/decode.py``
"""

from __future__ import annotations

import math
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib.core.frames import utc_fields_to_gps_ns  # noqa: E402
from drivers.hydrins.nav import NavRecord, status_words  # noqa: E402
from drivers.hydrins.nmea_decode import NmeaDecoder, NmeaNavAssembler  # noqa: E402
from drivers.hydrins.nmea_encode import encode_epoch, encode_zda  # noqa: E402
from drivers.hydrins.stdbin_decode import StdbinDecoder  # noqa: E402
from drivers.hydrins.stdbin_format import (  # noqa: E402
    BLOCK_SIZES,
    EXTENDED_NAVIGATION_BLOCKS,
    EXTERNAL_DATA_BLOCKS,
    NAVIGATION_BLOCKS,
)
from drivers.zf.assembler import ProfileAssembler  # noqa: E402
from drivers.zf.zfp1 import encode_profile  # noqa: E402

REAL = ROOT / "tests" / "data" / "real"


def best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def row(name: str, value: float, unit: str, peer_name: str, peer: float, goal: float) -> None:
    print(
        f"{name:<34} {value:>12,.0f} {unit:<13} peer {peer_name:<26} {peer:>12,.0f}  "
        f"ratio {value / peer:6.1f}x   goal {goal:,.0f} ({'met' if value >= goal else 'NOT met'})"
    )


# -- NMEA ---------------------------------------------------------------------------------------


def nmea_lines(epochs: int) -> list[bytes]:
    rng = np.random.default_rng(1)
    algo, system = status_words(navigation=True, fine_alignment=True, utc_detected=True, pps_detected=True)
    lines = []
    for k in range(epochs):
        gps_ns = utc_fields_to_gps_ns(2024, 6, 1, 36_000 * 10**9 + k * 10**8)
        nav = NavRecord(
            "nmea",
            gps_ns=gps_ns,
            lat_deg=45.5 + rng.normal() * 1e-4,
            lon_deg=-73.55 + rng.normal() * 1e-4,
            height_m=5.0,
            roll_rad=rng.normal() * 0.02,
            pitch_rad=rng.normal() * 0.02,
            heading_rad=1.0,
            v_north_m_s=2.0,
            v_east_m_s=0.5,
            v_down_m_s=0.0,
            surge_m=0.0,
            sway_m=0.0,
            heave_m=0.1,
            sigma_roll_rad=1e-4,
            sigma_pitch_rad=1e-4,
            sigma_heading_rad=2e-4,
            sigma_north_m=0.02,
            sigma_east_m=0.02,
            sigma_down_m=0.03,
            sigma_v_north_m_s=0.01,
            sigma_v_east_m_s=0.01,
            sigma_v_down_m_s=0.01,
            algorithm_status=algo,
            system_status=system,
            user_status=0,
        )
        lines += (encode_zda(gps_ns) + encode_epoch(nav)).splitlines(keepends=True)
    return lines


def bench_nmea() -> None:
    from pynmeagps import VALCKSUM, NMEAReader

    lines = nmea_lines(2000)  # 26 000 sentences
    blob = b"".join(lines)
    n = len(lines)

    def ours_stream():
        recs = NmeaDecoder().feed(blob)
        assert len(recs) == n

    def ours_lines():
        dec = NmeaDecoder()
        for line in lines:
            dec.feed(line)
        assert dec.stats.records == n

    def ours_nav():
        navs = NmeaNavAssembler(utc_clock=None).feed(blob)
        assert len(navs) == n // 13

    def peer():
        for line in lines:
            NMEAReader.parse(line, validate=VALCKSUM)

    t_peer = best_of(peer)
    peer_rate = n / t_peer
    row("NMEA sentences/s (stream)", n / best_of(ours_stream), "sentences/s", "pynmeagps", peer_rate, 50_000)
    row(
        "NMEA sentences/s (line by line)",
        n / best_of(ours_lines),
        "sentences/s",
        "pynmeagps",
        peer_rate,
        50_000,
    )
    row(
        "NMEA → nav records (sentences/s)",
        n / best_of(ours_nav),
        "sentences/s",
        "pynmeagps (no assembly)",
        peer_rate,
        50_000,
    )


# -- STDBIN -------------------------------------------------------------------------------------


def naive_stdbin(data: bytes) -> int:
    """Peer: walk the masks block by block with one struct call each (no compiled layouts)."""
    tables = (NAVIGATION_BLOCKS, EXTENDED_NAVIGATION_BLOCKS, EXTERNAL_DATA_BLOCKS)
    pos, frames = 0, 0
    while True:
        pos = data.find(b"IX", pos)
        if pos < 0 or len(data) - pos < 25:
            return frames
        version = data[pos + 2]
        if version == 3:
            nav, ext_nav, ext, size = struct.unpack_from(">IIIH", data, pos + 3)
            off = pos + 25
        else:
            nav, ext, size = struct.unpack_from(">IIH", data, pos + 3)
            ext_nav, off = 0, pos + 21
        if sum(data[pos : pos + size - 4]) & 0xFFFFFFFF != struct.unpack_from(">I", data, pos + size - 4)[0]:
            pos += 1
            continue
        blocks = {}
        for mask, table in zip((nav, ext_nav, ext), tables):
            for bit in range(32):
                if mask >> bit & 1:
                    name, fmt, names = table[bit]
                    blocks[name] = dict(zip(names, struct.unpack_from(">" + fmt, data, off)))
                    off += BLOCK_SIZES[name]
        frames += 1
        pos += size


def bench_stdbin() -> None:
    one = (REAL / "ixblue-stdbin" / "log_STDBIN_V3.log").read_bytes()
    reps = 120
    blob = one * reps  # 2040 real V3 frames (~730 bytes, 37 blocks each)
    n = 17 * reps

    def ours():
        assert len(StdbinDecoder().feed(blob)) == n

    def peer():
        assert naive_stdbin(blob) == n

    row(
        "STDBIN V3 frames/s",
        n / best_of(ours),
        "frames/s",
        "per-block struct decoder",
        n / best_of(peer),
        20_000,
    )


# -- ZFP1 ---------------------------------------------------------------------------------------


def naive_zfp(dgs: list[bytes]) -> int:
    """Peer: pure-Python packet decoding, one tuple per point."""
    pts = 0
    for d in dgs:
        h = struct.unpack_from("<4sHHIHHqIiiHH", d)
        assert zlib.crc32(d[:-4]) == int.from_bytes(d[-4:], "little")
        ranges = [r * 1e-4 if r else math.nan for r, _ in struct.iter_unpack("<IH", d[40:-4])]
        pts += len(ranges)
        assert len(ranges) == h[10]
    return pts


def bench_zfp() -> None:
    rng = np.random.default_rng(2)
    n_profiles, n_points = 200, 5080
    dgs = []
    for c in range(n_profiles):
        dgs += encode_profile(
            c,
            10**18 + c * 5_000_000,
            984,
            0,
            70866,
            rng.integers(0, 3_000_000, n_points),
            rng.integers(0, 65535, n_points),
        )
    total = n_profiles * n_points

    def ours():
        asm = ProfileAssembler()
        profiles = [p for d in dgs for p in asm.feed(d)]
        assert len(profiles) == n_profiles

    def peer():
        assert naive_zfp(dgs) == total

    row(
        "ZFP1 points/s (decode+assemble)",
        total / best_of(ours, 5),
        "points/s",
        "pure-Python struct decoder",
        total / best_of(peer, 1),
        20_000_000,
    )


if __name__ == "__main__":
    print(f"decode benchmarks — Python {sys.version.split()[0]}, numpy {np.__version__}, one core")
    bench_nmea()
    bench_stdbin()
    bench_zfp()

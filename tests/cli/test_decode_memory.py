"""``mls decode`` streams its file: a capture or dump far larger than the memory it uses.

Each decode runs in a child process that first decodes a small file with the same command (so
imports, caches and one-off allocations are in its baseline), then the large file, and reports
the growth of its peak resident set (``ru_maxrss``) over that baseline.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.zf.zfp1 import encode_profile
from tests.drivers.helpers import real_file

MB = 1 << 20
CHILD = """
import resource, sys
from cli.app import app
small, args = sys.argv[1], sys.argv[2:]
app(["decode", small, *args[2:]], standalone_mode=False)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
code = app(args, standalone_mode=False)
print("GROWTH_KB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base, code, file=sys.stderr)
"""


def _decode_in_child(small: Path, big: Path, *options: str) -> tuple[int, str, str, str]:
    """(peak growth in bytes, exit status, stdout, stderr) of ``mls decode big options`` in a
    fresh process."""
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(small), "decode", str(big), *options],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).parents[2],
    )
    (line,) = [ln for ln in proc.stderr.splitlines() if ln.startswith("GROWTH_KB")]
    _, growth_kb, code = line.split()
    return int(growth_kb) * 1024, code, proc.stdout, proc.stderr


def _capture_blocks(path: Path) -> tuple[bytes, list[bytes]]:
    """(section + interface headers, the packet blocks) of a little-endian pcapng file."""
    data = path.read_bytes()
    head, packets, pos = b"", [], 0
    while pos < len(data):
        btype, blen = struct.unpack_from("<II", data, pos)
        if btype == 6:
            packets.append(data[pos : pos + blen])
        elif btype in (0x0A0D0D0A, 1):
            head += data[pos : pos + blen]
        pos += blen
    return head, packets


def test_a_200_mb_capture_decodes_in_bounded_memory(tmp_path):
    """~200 MB of the real V3 capture's packets repeated: ~430 000 STDBIN frames."""
    small = real_file("ixblue-stdbin", "stdbin_V3_2Hz.pcapng")
    head, packets = _capture_blocks(small)
    body = b"".join(packets)
    reps = 200 * MB // len(body)
    big = tmp_path / "big.pcapng"
    with big.open("wb") as f:
        f.write(head)
        for _ in range(reps):
            f.write(body)
    size = big.stat().st_size
    try:
        growth, code, out, err = _decode_in_child(small, big, "-f", "pcapng", "--port", "8200")
    finally:
        big.unlink()
    n = reps * len(packets)
    assert (
        code == "None"
        and f"summary: {n} records;" in out
        and f"capture: {n} packets, {n} UDP datagrams decoded" in out
    ), err
    assert growth < size // 10, f"peak grew by {growth / MB:.1f} MB decoding {size / MB:.0f} MB"


@pytest.mark.parametrize("fmt", ["zfp", "nmea"])
def test_a_64_mb_dump_or_log_decodes_in_bounded_memory(tmp_path, fmt):
    """ZFP1 profiles back to back, or an NMEA log that is one 64 MB line of binary garbage (no
    record in it: exit status 2)."""
    small, big = tmp_path / "small", tmp_path / "big"
    if fmt == "zfp":
        rng = np.random.default_rng(3)
        profiles = [
            b"".join(
                encode_profile(
                    c,
                    10**18 + c * 5_000_000,
                    984,
                    0,
                    70866,
                    rng.integers(1, 3_000_000, 5080),
                    rng.integers(0, 65535, 5080),
                )
            )
            for c in range(64)
        ]
        small.write_bytes(profiles[0])
        one = b"".join(profiles)
    else:
        small.write_bytes(real_file("openrvdas-nbp1406", "NBP1406_s330-2014-08-01").read_bytes()[:4096])
        one = np.random.default_rng(3).integers(0, 256, 4 * MB, np.uint8)
        one = one[(one != 10) & (one != 13)].tobytes()  # no line terminator anywhere
    with big.open("wb") as f:
        for _ in range(64 * MB // len(one) + 1):
            f.write(one)
    size = big.stat().st_size
    growth, code, out, err = _decode_in_child(small, big, "-f", fmt)
    big.unlink()
    if fmt == "zfp":
        assert code == "None" and "profile" in out, err
    else:
        assert code == "2" and f"no valid nmea record in {size} bytes" in err
    assert growth < size // 8, f"peak grew by {growth / MB:.1f} MB decoding {size / MB:.0f} MB"

"""``mls decode`` names the real reason an input cannot be decoded: a directory, a FIFO, a
capture whose packet timestamp overflows 64-bit nanoseconds — one line, exit 2, no traceback."""

from __future__ import annotations

import os
import struct

from typer.testing import CliRunner

from cli.app import app
from tests.drivers.helpers import real_file

runner = CliRunner(env={"COLUMNS": "400"})
EPB = 6


def _first_epb_offset(data: bytes) -> int:
    pos = 0
    while pos + 8 <= len(data):
        btype, blen = struct.unpack_from("<II", data, pos)
        if btype == EPB:
            return pos
        pos += blen
    raise AssertionError("no enhanced packet block")


def _one_line_error(res) -> str:
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    (line,) = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    return line


def test_a_directory_is_named_as_one(tmp_path):
    res = runner.invoke(app, ["decode", str(tmp_path), "-f", "stdbin"])
    line = _one_line_error(res)
    assert f"{tmp_path}: is a directory" in line and "no such file" not in res.output


def test_a_fifo_is_not_a_regular_file_and_is_not_opened(tmp_path):
    fifo = tmp_path / "stream"
    os.mkfifo(fifo)  # opening it for reading would block with no writer: it must not be opened
    res = runner.invoke(app, ["decode", str(fifo), "-f", "nmea"])
    line = _one_line_error(res)
    assert f"{fifo}: not a regular file (a FIFO)" in line


def test_a_missing_file_is_still_no_such_file(tmp_path):
    res = runner.invoke(app, ["decode", str(tmp_path / "nope.bin"), "-f", "stdbin"])
    assert "no such file" in _one_line_error(res)


def test_a_pcapng_timestamp_beyond_int64_ns_names_the_packet_and_the_value(tmp_path):
    data = bytearray(real_file("ixblue-stdbin", "stdbin_V5_2Hz.pcapng").read_bytes())
    at = _first_epb_offset(bytes(data))
    struct.pack_into("<II", data, at + 12, 0xFFFFFFFF, 0xFFFFFFFF)  # timestamp high, low words
    bad = tmp_path / "huge.pcapng"
    bad.write_bytes(bytes(data))
    for extra in (["--timing"], ["--json"], []):
        res = runner.invoke(app, ["decode", str(bad), "-f", "pcapng", "--payload", "stdbin", *extra])
        line = _one_line_error(res)
        assert f"packet 1 at offset {at}: timestamp {2**64 - 1} ticks at 1000000 per s" in line, line
        assert "beyond 64-bit nanoseconds" in line

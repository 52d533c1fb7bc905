"""A session writer in its own process, for the kill -9 tests (not a test module).

    python writer_proc.py ROOT LEDGER FLUSH_S ROTATE_BYTES

Prints ``READY <session dir>`` and then submits records on three channels as fast as a 1 ms
pace allows. After each submit it appends ``topic seq t_submit_ns`` to LEDGER with one
unbuffered write (page cache: it survives the kill), so the test knows what was emitted when.
"""

from __future__ import annotations

import os
import sys
import time

from acquire.log.session import SessionOptions
from acquire.log.sessionlog import SessionWriter


def payload(seq: int, n: int) -> bytes:
    return bytes((seq * 31 + k * 7) % 256 for k in range(n))


def main() -> None:
    root, ledger, flush_s, rotate_bytes = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
    w = SessionWriter(
        root,
        "killtest",
        SessionOptions(flush_s=flush_s, fsync_s=1.0, rotate_bytes=rotate_bytes, compression="lz4"),
    )
    sd = w.start()
    fd = os.open(ledger, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    print(f"READY {sd}", flush=True)
    seq = 0
    while True:
        seq += 1
        for topic, data in (
            ("/ins/raw", payload(seq, 80 + seq % 50)),
            ("/lidar/raw", payload(seq, 1400)),
            ("/ins/nav", {"seq": seq, "roll_rad": seq * 1e-4}),
        ):
            t = time.monotonic_ns()
            w.submit(topic, data, host_ns=t)
            os.write(fd, f"{topic} {seq} {t}\n".encode())
        time.sleep(0.001)


if __name__ == "__main__":
    main()

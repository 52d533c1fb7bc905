"""Recorded files streamed into the decoders: ZFP1 dumps split into packets whatever the reads."""

from __future__ import annotations

import random

import numpy as np

from drivers.base import DecoderStats
from drivers.capture.files import ZfpPacketSplitter
from drivers.zf.zfp1 import encode_profile


def test_zfp_dump_split_the_same_whatever_the_piece_sizes():
    dgs = encode_profile(
        7, 10**18, 1000, 0, 100, np.arange(1, 401, dtype=np.uint32), np.zeros(400, np.uint16)
    )
    cut = dgs[-1][:-10]  # the dump ends inside a packet
    data = b"junkZF" + dgs[0] + b"ZFP" + b"".join(dgs[1:-1]) + b"Z" + cut
    skipped = len(b"junkZF") + len(b"ZFP") + len(b"Z") + len(cut)
    rng = random.Random(5)
    for sizes in ([len(data)], [1] * len(data), None):
        stats = DecoderStats()
        splitter = ZfpPacketSplitter(stats)
        got, pos = [], 0
        while pos < len(data):
            n = sizes.pop(0) if sizes else rng.randint(1, 3000)
            got += splitter.feed(data[pos : pos + n])
            pos += n
        splitter.flush()
        assert got == dgs[:-1]
        assert stats.skipped_bytes == skipped and dict(stats.rejected) == {"truncated": 1}

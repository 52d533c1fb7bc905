"""The profiler's datagrams of a session, decoded once (``mls export``, the Foxglove export).

:func:`iter_packets` walks ``/lidar/raw`` (:func:`acquire.log.read.iter_messages`), decodes each
datagram with the codec its channel names (:func:`packet_codec`), drops a duplicated datagram
(it follows its original within 4096 datagrams) and times the packet's points: point i at
``t0 + i·dt`` when the packet says PPS-locked and time-valid, else its last point at its
receipt (``receipt_ns``: the record's log time unless the caller re-times it). Counters:
``packets`` (decoded, once each), ``bad`` (undecodable), ``unsynced`` (timed by the receipt).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from acquire.log.read import SessionReadError, iter_messages


def packet_codec(protocol: str):
    from drivers.zf.zfp1 import ZFP1

    codecs = {"zfp1": ZFP1}
    if protocol not in codecs:
        raise SessionReadError(
            f"/lidar/raw: protocol {protocol!r} has no decoder here (known: {', '.join(codecs)})"
        )
    return codecs[protocol]


def iter_packets(
    session: Path, protocol: str, counts: dict, receipt_ns: Callable | None = None, progress=None
) -> Iterator[tuple]:
    """``(record, packet, point index array, point GPS ns array)`` of every datagram with points
    (module docstring)."""
    from drivers.base import DriverError

    codec = packet_codec(protocol)
    seen: set[tuple[int, int, int]] = set()
    recent: deque[tuple[int, int, int]] = deque()
    for counter in ("packets", "bad", "unsynced"):
        counts.setdefault(counter, 0)
    for env in iter_messages(session, {"/lidar/raw"}, progress):
        try:
            pk = codec.decode_packet(env.payload)
        except DriverError:
            counts["bad"] += 1
            continue
        key = (pk.profile_counter, pk.packet_index, pk.t0_ns)
        if key in seen:
            continue  # a duplicated datagram
        seen.add(key)
        recent.append(key)
        if len(recent) > 4096:
            seen.discard(recent.popleft())
        counts["packets"] += 1
        n = pk.n_points
        if n == 0:
            continue
        i = np.arange(n, dtype=np.int64)
        if pk.pps_locked and pk.time_valid:
            t = pk.t0_ns + i * pk.dt_ns
        else:  # its last point at its receipt
            counts["unsynced"] += 1
            t = (env.log_time_ns if receipt_ns is None else receipt_ns(env)) - (n - 1 - i) * pk.dt_ns
        yield env, pk, i, t

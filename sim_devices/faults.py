"""Fault timelines: what the emulated devices do wrong, and when (a YAML file).

    # faults.yaml — times in seconds of scenario time after the start of the run window
    seed: 7                       # optional: random draws of the probabilistic faults
    faults:
      - {at_s: 5.0,  kind: serial_unplug, duration_s: 2.0}    # close the pty; a new one after 2 s
      - {at_s: 8.0,  kind: garbage, bytes: 200}                # line noise between two epochs
      - {at_s: 9.0,  kind: bad_checksum, duration_s: 0.5}      # every sentence/frame corrupted
      - {at_s: 10.0, kind: udp_loss, device: profiler, duration_s: 1.0, probability: 0.2}
      - {at_s: 11.0, kind: udp_reorder, device: profiler, duration_s: 1.0}
      - {at_s: 12.0, kind: udp_duplicate, device: pps, duration_s: 3.0}
      - {at_s: 15.0, kind: pps_loss, duration_s: 3.0}
      - {at_s: 20.0, kind: profiler_clock_offset, offset_s: 1.0, duration_s: 5.0}
      - {at_s: 30.0, kind: profiler_clock_drift, drift_ppm: 100.0, duration_s: 10.0}
      - {at_s: 40.0, kind: ins_latency_jump, latency_s: 0.02, duration_s: 5.0}
      - {at_s: 50.0, kind: gnss_outage, duration_s: 20.0}
      - {at_s: 75.0, kind: zda_late, delay_s: 0.8, duration_s: 2.0}   # ZDA 800 ms later than usual
      - {at_s: 80.0, kind: leap_second, gps_minus_utc_s: 19}          # the INS believes GPS − UTC = 19 s
      - {at_s: 85.0, kind: host_clock_step, step_s: -3600.0}          # the host's realtime clock steps

Kinds (:data:`KINDS`; ``device`` defaults to the only device a kind applies to):

- ``serial_unplug`` (ins): the pty master and slave are closed and the ``<run dir>/ins`` link
  removed; after ``duration_s`` (absent: never) a new pty is opened and the link moved to it.
- ``garbage`` (ins): ``bytes`` random bytes (default 64) written at ``at_s``; they never
  contain a sentence/frame start, a line end or white space, so a decoder skips exactly them.
- ``bad_checksum`` (ins): every sentence (NMEA, ZDA included) or frame (STDBIN) emitted in the
  window is sent with a wrong checksum, each with ``probability`` (default 1).
- ``udp_loss`` / ``udp_reorder`` / ``udp_duplicate`` (profiler or pps, ``device`` required):
  each datagram emitted in the window is dropped / held back and sent after the next one /
  sent twice, with ``probability`` (default 1).
- ``pps_loss`` (pps): no pulse in the window (the pulse counter does not advance).
- ``profiler_clock_offset`` (profiler): the profiler's clock is ``offset_s`` (default 1.0)
  ahead during the window; ``pps_locked`` (default true: the profiler believes it is synced).
- ``profiler_clock_drift`` (profiler): the profiler's clock runs ``drift_ppm`` fast from
  ``at_s`` (the error grows from 0) and is re-synced at the end; ``pps_locked`` default false.
- ``ins_latency_jump`` (ins): ``latency_s`` more output latency during the window.
- ``gnss_outage`` (ins): GNSS lost: INS status dead reckoning (GPS received/valid cleared),
  position error growing at ``position_drift_m_s`` (default 0.05) along north, σ growing alike.
- ``zda_late`` (ins, NMEA): each ZDA of a second in the window leaves ``delay_s`` later than
  usual (its ``zda_delay_s`` after the pulse) — past the usual latency, possibly past the next
  pulse.
- ``leap_second`` (ins): from ``at_s`` (to the window's end) the INS believes GPS − UTC is
  ``gps_minus_utc_s`` (an integer of seconds, 0–255): its UTC tags (ZDA, TIME__; STDBIN validity
  time and system date) are made with it, and an NMEA INS announces it (``$PMLS,GPSUTC``, before
  each ZDA and before the first epoch tagged with a new count, for the whole run when the
  timeline has such a fault; the table's count outside the window). A STDBIN INS has no
  announcement: only its tags move.
- ``host_clock_step`` (host, instantaneous): the host's ``CLOCK_REALTIME`` steps by ``step_s``
  (|step| ≥ 0.01 s) at ``at_s``. Simulated: the emulators cannot step this machine's clock, so
  they write the step to ``<run dir>/host_clock`` and a daemon given that file
  (``mls acquire --sim-host-clock FILE``) sees it through the interface it reads
  realtime − monotonic with (:class:`drivers.timing.FakeHostClock`: the offset and the kernel
  stamps taken after the step move; monotonic time does not).

A fault acts on what the device emits from ``at_s`` to ``at_s + duration_s`` (half-open; a
fault without ``duration_s`` lasts to the end of the run), on the devices' GPS time scale: the
profiler's clock faults on each profile's measurement time, ``gnss_outage``,
``ins_latency_jump`` and ``leap_second`` on the INS epoch's time tag, ``pps_loss`` and
``zda_late`` on the pulse's GPS second, the link faults (unplug, garbage, checksums, UDP) and
``host_clock_step`` on the truth-clock instant. Two faults of one
kind on one device must not overlap. Errors name the file, line, column and key
(``faults.yaml:7:5: faults[2].probability: got 1.5, expected a number ≤ 1``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calib.io.configfile import ConfigError, Node, load_yaml

NS_PER_S = 1_000_000_000
#: the "device" of the faults of the host itself (no emulator process: the run applies them)
HOST = "host"

#: kind → (devices it applies to, {optional key: default}); ``duration_s`` is handled apart.
KINDS: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "serial_unplug": (("ins",), {}),
    "garbage": (("ins",), {"bytes": 64}),
    "bad_checksum": (("ins",), {"probability": 1.0}),
    "udp_loss": (("profiler", "pps"), {"probability": 1.0}),
    "udp_reorder": (("profiler", "pps"), {"probability": 1.0}),
    "udp_duplicate": (("profiler", "pps"), {"probability": 1.0}),
    "pps_loss": (("pps",), {}),
    "profiler_clock_offset": (("profiler",), {"offset_s": 1.0, "pps_locked": True}),
    "profiler_clock_drift": (("profiler",), {"drift_ppm": None, "pps_locked": False}),
    "ins_latency_jump": (("ins",), {"latency_s": None}),
    "gnss_outage": (("ins",), {"position_drift_m_s": 0.05}),
    "zda_late": (("ins",), {"delay_s": None}),
    "leap_second": (("ins",), {"gps_minus_utc_s": None}),
    "host_clock_step": ((HOST,), {"step_s": None}),
}
#: kinds that happen at one instant (no window)
INSTANT = frozenset({"garbage", "host_clock_step"})
#: kinds that need a window
NEEDS_DURATION = frozenset({"bad_checksum", "udp_loss", "udp_reorder", "udp_duplicate"})


class FaultError(ConfigError):
    """A fault timeline that cannot be used (the message names the file, line and key)."""


@dataclass(frozen=True)
class Fault:
    kind: str
    device: str
    at_s: float  # scenario seconds after the start of the run window
    duration_s: float | None  # None: to the end of the run; 0 for instantaneous kinds
    params: dict = field(default_factory=dict)
    where: str = ""  # "faults.yaml:7:5: faults[2]" (for errors found later)

    @property
    def end_s(self) -> float:
        return math.inf if self.duration_s is None else self.at_s + self.duration_s

    def window_ns(self, start_gps_ns: int) -> tuple[int, int | None]:
        """[start, end) in GPS ns (end None: open)."""
        t0 = start_gps_ns + round(self.at_s * NS_PER_S)
        return t0, None if self.duration_s is None else t0 + round(self.duration_s * NS_PER_S)


@dataclass(frozen=True)
class FaultPlan:
    faults: tuple[Fault, ...] = ()
    seed: int = 0
    source: str | None = None

    def for_device(self, device: str) -> list[Fault]:
        return [f for f in self.faults if f.device == device]

    def check_window(self, duration_s: float) -> None:
        """Every fault must start inside a run window of ``duration_s`` scenario seconds."""
        for f in self.faults:
            if f.at_s >= duration_s:
                raise FaultError(
                    f"{f.where}.at_s: got {f.at_s:g}, expected < {duration_s:g} "
                    f"(the run window's length in scenario seconds)"
                )

    def schedule(self, start_gps_ns: int, clock=None) -> list[dict]:
        """JSON-ready list: every fault with its window in scenario seconds, GPS ns and (with a
        :class:`~sim_devices.clock.TruthClock`) host monotonic ns."""
        out = []
        for f in self.faults:
            g0, g1 = f.window_ns(start_gps_ns)
            row = {
                "kind": f.kind,
                "device": f.device,
                "at_s": f.at_s,
                "duration_s": f.duration_s,
                "start_gps_ns": g0,
                "end_gps_ns": g1,
                **f.params,
            }
            if clock is not None:
                row["start_host_ns"] = clock.host_ns(g0)
                row["end_host_ns"] = None if g1 is None else clock.host_ns(g1)
            row["where"] = f.where
            out.append(row)
        return out


class Timeline:
    """The faults of one device as GPS-ns windows, for quick ``active(kind, t)`` queries."""

    def __init__(self, faults: list[Fault], start_gps_ns: int) -> None:
        self.windows: dict[str, list[tuple[int, float, Fault]]] = {}
        for f in faults:
            g0, g1 = f.window_ns(start_gps_ns)
            self.windows.setdefault(f.kind, []).append((g0, math.inf if g1 is None else g1, f))
        for w in self.windows.values():
            w.sort(key=lambda x: x[0])

    def active(self, kind: str, t_gps_ns: int) -> Fault | None:
        for g0, g1, f in self.windows.get(kind, ()):
            if g0 <= t_gps_ns < g1:
                return f
        return None

    def started_at(self, kind: str, t_gps_ns: int) -> int | None:
        """GPS ns at which the active fault of ``kind`` started (None if none is active)."""
        for g0, g1, _ in self.windows.get(kind, ()):
            if g0 <= t_gps_ns < g1:
                return g0
        return None

    def events(self, kind: str) -> list[tuple[int, float, Fault]]:
        return list(self.windows.get(kind, ()))


# -- loading ------------------------------------------------------------------------------------


def _datagram_bytes(n: Node) -> int:
    value = n.integer(minimum=1)
    if value > 65536:
        raise n.fail("an integer ≤ 65536")
    return value


def _drift_ppm(n: Node) -> float:
    value = n.number(minimum=-1e5, maximum=1e5)
    if value == 0:
        raise n.fail("a non-zero drift in ppm")
    return value


def _step_s(n: Node) -> float:
    value = n.number(minimum=-1e9, maximum=1e9)
    if abs(value) < 0.01:
        raise n.fail("a step of at least 0.01 s either way (smaller ones are slewed)")
    return value


def _position_drift_m_s(n: Node) -> float:
    return n.number(minimum=0.0, maximum=100.0)


#: option key → its reader (a key not here: ``position_drift_m_s``)
_PARAM_READERS: dict[str, Callable[[Node], Any]] = {
    "probability": lambda n: n.number(minimum=0.0, maximum=1.0, exclusive_minimum=True),
    "bytes": _datagram_bytes,
    "pps_locked": lambda n: n.boolean(),
    "drift_ppm": _drift_ppm,
    "latency_s": lambda n: n.number(minimum=0.0, maximum=10.0, exclusive_minimum=True),
    "offset_s": lambda n: n.number(minimum=-1e6, maximum=1e6),
    "delay_s": lambda n: n.number(minimum=0.0, maximum=10.0, exclusive_minimum=True),
    "gps_minus_utc_s": lambda n: n.integer(minimum=0, maximum=255),
    "step_s": _step_s,
}


def _check_fault_keys(m: dict[str, Node], kind: str, options: dict[str, Any]) -> None:
    """Every key one of this kind's."""
    allowed = {"at_s", "kind", "device", *options} | ({"duration_s"} if kind not in INSTANT else set())
    for key in m:
        if key not in allowed:
            raise FaultError(
                f"{m[key].where()}: not a key of a {kind} fault; allowed: {', '.join(sorted(allowed))}"
            )


def _fault_device(m: dict[str, Node], kind: str, devices: tuple[str, ...], where: str) -> str:
    """The device named, or the kind's only one."""
    if "device" in m:
        return m["device"].string(choices=devices)
    if len(devices) == 1:
        return devices[0]
    raise FaultError(f"{where}: a {kind} fault needs 'device' (one of {', '.join(devices)})")


def _fault_duration(m: dict[str, Node], kind: str, where: str) -> float | None:
    """``duration_s``; 0 for an instantaneous kind, None (to the run's end) when not given."""
    duration = 0.0 if kind in INSTANT else None
    if "duration_s" in m:
        duration = m["duration_s"].number(minimum=0.0, exclusive_minimum=True)
    elif kind in NEEDS_DURATION:
        raise FaultError(f"{where}: a {kind} fault needs 'duration_s' (seconds, > 0)")
    return duration


def _fault_params(m: dict[str, Node], kind: str, options: dict[str, Any], where: str) -> dict[str, Any]:
    """The kind's options, read or defaulted (one without a default is required)."""
    params: dict[str, Any] = {}
    for key, default in options.items():
        if key in m:
            params[key] = _PARAM_READERS.get(key, _position_drift_m_s)(m[key])
        elif default is None:
            raise FaultError(f"{where}: a {kind} fault needs {key!r}")
        else:
            params[key] = default
    return params


def _fault(node: Node) -> Fault:
    where = node.where()
    m = node.mapping(
        required={"at_s", "kind"},
        optional={"device", "duration_s", *{k for _, o in KINDS.values() for k in o}},
    )
    kind = m["kind"].string(choices=KINDS)
    devices, options = KINDS[kind]
    _check_fault_keys(m, kind, options)
    at_s = m["at_s"].number(minimum=0.0)
    device = _fault_device(m, kind, devices, where)
    duration = _fault_duration(m, kind, where)
    params = _fault_params(m, kind, options, where)
    return Fault(kind, device, at_s, duration, params, where)


def faults_from_node(root: Node) -> FaultPlan:
    top = root.mapping(required={"faults"}, optional={"seed"})
    seed = top["seed"].integer(minimum=0) if "seed" in top else 0
    faults = [_fault(n) for n in top["faults"].sequence()]
    by_key: dict[tuple[str, str], list[Fault]] = {}
    for f in faults:
        by_key.setdefault((f.kind, f.device), []).append(f)
    for group in by_key.values():
        group.sort(key=lambda f: f.at_s)
        for a, b in itertools.pairwise(group):
            if b.at_s < a.end_s or (a.kind in INSTANT and b.at_s == a.at_s):
                raise FaultError(
                    f"{b.where}: {b.kind} on {b.device} at {b.at_s:g} s overlaps "
                    f"the one at {a.where.split(': ')[-1]} ({a.at_s:g} s to "
                    f"{a.end_s:g} s)"
                )
    return FaultPlan(tuple(sorted(faults, key=lambda f: f.at_s)), seed, root.source)


def load_faults(path: str | Path) -> FaultPlan:
    """Read and validate a fault timeline (raises :class:`FaultError` / ``ConfigError``)."""
    try:
        return faults_from_node(load_yaml(path))
    except FaultError:
        raise
    except ConfigError as e:
        raise FaultError(str(e)) from None


def parse_faults(text: str, source: str = "faults.yaml") -> FaultPlan:
    try:
        return faults_from_node(load_yaml(text, source=source))
    except FaultError:
        raise
    except ConfigError as e:
        raise FaultError(str(e)) from None

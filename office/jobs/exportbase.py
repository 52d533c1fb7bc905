"""What ``mls export`` is asked and what it gives (:mod:`office.jobs.export`): the options, the
error, the pass windows and the result, shared by the jobs that read a session
(:mod:`office.jobs.sessionread`, :mod:`office.jobs.sessionnav`, :mod:`office.jobs.foxglove`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from acquire.errors import AcquireError

PASS_SOURCES = ("auto", "events", "plan")


class ExportError(AcquireError, ValueError):
    """The session cannot be exported as asked (the message says why and what to do)."""


@dataclass(frozen=True)
class ExportOptions:
    passes: str = "auto"  # auto: events when the session has marks, else the plan
    site_file: Path | None = None  # overrides the site file stored in the session
    max_cross_track_m: float = 5.0  # plan: distance from the planned line
    max_heading_error_deg: float = 20.0  # plan: heading against the line's
    min_pass_s: float = 3.0  # plan: shorter stretches are not passes
    max_gap_s: float = 1.0  # trajectory gap that breaks interpolation (bundle reader's)
    laz_dir: Path | None = None
    sbet_path: Path | None = None
    require_complete: bool = False  # refuse a session with a segment that did not end normally

    def __post_init__(self) -> None:
        if self.passes not in PASS_SOURCES:
            raise ExportError(f"passes {self.passes!r}: expected one of {', '.join(PASS_SOURCES)}")


@dataclass(frozen=True)
class PassWindow:
    pass_id: int
    start_gps_ns: int
    end_gps_ns: int
    source: str  # "can:marks", "mqtt", "plan"


@dataclass
class ExportResult:
    bundle: Path
    epochs: int
    epochs_from_clock: int  # epochs whose time came from the clock model (INS not synced)
    points: int
    points_per_pass: dict[int, int]
    returns_outside_passes: int
    packets: int
    packets_unsynced: int  # datagrams timed by the clock model (no PPS-locked time tag)
    pass_source: str  # "events" or "plan"
    passes: list[PassWindow]
    warnings: list[str] = field(default_factory=list)
    laz: list = field(default_factory=list)  # calib georef PassOutput per pass
    sbet: Path | None = None

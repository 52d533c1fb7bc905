"""What a check returns and how the checks add up to ``mls doctor``'s exit status."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import Enum
from typing import Any

#: exit status of ``mls doctor``: ready, ready with warnings, not ready
EXIT_READY, EXIT_WARNINGS, EXIT_NOT_READY = 0, 1, 2
REPORT_FORMAT = 1


class Status(str, Enum):
    """``ok`` passed; ``warn`` the survey can run but something should be looked at (or could
    not be judged); ``fail`` not ready; ``skip`` not applicable here (or judged elsewhere)."""

    OK = "ok"
    WARN = "warn"
    FAIL = "fail"
    SKIP = "skip"


@dataclass(frozen=True, kw_only=True)
class CheckResult:
    """One line of ``mls doctor``: ``message`` what was found, ``advice`` what to do (empty when
    nothing is to be done), ``data`` the measured values (units in the keys)."""

    name: str  # the check: config, ports, serial, pps, clock, udp_buffer, disk, broker, leap_table, unit
    status: Status
    message: str
    advice: str = ""
    device: str | None = None  # the config's device name, for per-device checks
    data: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["status"] = self.status.value
        return d


def ok(name: str, message: str, **kw: Any) -> CheckResult:
    return CheckResult(name=name, status=Status.OK, message=message, **kw)


def warn(name: str, message: str, advice: str, **kw: Any) -> CheckResult:
    return CheckResult(name=name, status=Status.WARN, message=message, advice=advice, **kw)


def fail(name: str, message: str, advice: str, **kw: Any) -> CheckResult:
    return CheckResult(name=name, status=Status.FAIL, message=message, advice=advice, **kw)


def skip(name: str, message: str, **kw: Any) -> CheckResult:
    return CheckResult(name=name, status=Status.SKIP, message=message, **kw)


def exit_code(results: list[CheckResult]) -> int:
    """2 when any check failed, 1 when any warned, else 0."""
    statuses = {r.status for r in results}
    if Status.FAIL in statuses:
        return EXIT_NOT_READY
    return EXIT_WARNINGS if Status.WARN in statuses else EXIT_READY


@dataclass(frozen=True, kw_only=True)
class DoctorReport:
    """All the checks of one run, and the running daemon's view when it runs."""

    config: str
    hours: float
    software_version: str
    software_prefix: str
    checks: list[CheckResult]
    live: dict[str, Any] | None = None

    @property
    def exit_code(self) -> int:
        return exit_code(self.checks)

    def as_dict(self) -> dict[str, Any]:
        """``mls doctor --json`` (docs/doctor.md, field by field)."""
        code = self.exit_code
        counts = {s.value: sum(r.status == s for r in self.checks) for s in Status}
        return {
            "format": REPORT_FORMAT,
            "ready": code != EXIT_NOT_READY,
            "exit_code": code,
            "status": {EXIT_READY: "ready", EXIT_WARNINGS: "warnings"}.get(code, "not_ready"),
            "counts": counts,
            "config": self.config,
            "hours": self.hours,
            "software": {"version": self.software_version, "prefix": self.software_prefix},
            "checks": [r.as_dict() for r in self.checks],
            "live": self.live,
        }

"""The config and its ports, judged from what ``mls acquire --check`` found (the command itself
runs: the same validation, the same startup checks of the guidance and the mount watch, the same
test-bind of every port the daemon listens on; ``cli/commands/doctor_cmd.py`` captures it)."""

from __future__ import annotations

from dataclasses import dataclass, field

from acquire.doctor.result import CheckResult, fail, ok, skip

#: ``mls acquire``'s exit statuses (cli/commands/acquire_cmd.py)
ACQUIRE_OK, ACQUIRE_PORTS_BUSY, ACQUIRE_BAD_CONFIG = 0, 1, 2


@dataclass(frozen=True, kw_only=True)
class AcquireCheck:
    """The outcome of ``mls acquire --config X --check``: its exit status, its stderr lines
    (one error per line) and its stdout (the devices table, what the guidance and the watch
    will do)."""

    exit_code: int
    errors: list[str] = field(default_factory=list)
    output: list[str] = field(default_factory=list)


def _notes(check: AcquireCheck) -> list[str]:
    return [ln.strip() for ln in check.output if ln.startswith(("guidance:", "mount watch:"))]


def config_result(check: AcquireCheck, config: str) -> CheckResult:
    if check.exit_code == ACQUIRE_BAD_CONFIG:
        errors = [e for e in check.errors if e.strip()]
        return fail(
            "config",
            f"{config}: not valid: {errors[-1] if errors else 'mls acquire --check exit 2'}",
            "fix each line above (file:line:column, key, what is expected), then run mls doctor "
            f"again; `mls acquire --config {config} --check` shows the same",
            data={"errors": errors},
        )
    return ok("config", f"{config} valid", data={"notes": _notes(check)})


def ports_result(check: AcquireCheck, daemon_pid: int | None) -> CheckResult:
    """Every port free; taken ports are no fault when the running daemon holds them."""
    if check.exit_code == ACQUIRE_BAD_CONFIG:
        return skip("ports", "not checked: the config is not valid")
    busy = [e for e in check.errors if "cannot bind" in e]
    if check.exit_code == ACQUIRE_OK or not busy:
        return ok("ports", "every port the daemon listens on is free")
    if daemon_pid is not None:
        return ok(
            "ports",
            f"{len(busy)} port(s) held, by the running daemon (pid {daemon_pid})",
            data={"busy": busy},
        )
    return fail(
        "ports",
        f"{len(busy)} port(s) taken: {busy[0]}",
        "stop the process that listens there (`ss -lunp` names it) or change the port in the config",
        data={"busy": busy},
    )

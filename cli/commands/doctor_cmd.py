"""``mls doctor [--config vessel.yaml] [--json]``: the pre-flight of the vessel PC (docs/doctor.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from cli.options import json_option, vessel_config_option

DEFAULT_CONFIG = Path("/etc/mls/vessel.yaml")

HELP = (
    "Pre-flight of the vessel PC before a survey: one line per check, and what to do when it "
    "fails.\n\n"
    "Checks: the config valid and every port free (what mls acquire --check does); each serial "
    "device present and openable by the daemon's user (mls, group dialout); the PPS present and "
    "pulsing (kernel, serial line or UDP); the host clock disciplined (chrony, else "
    "timedatectl; 'unknown' when neither answers); the UDP receive buffer (net.core.rmem_max ≥ "
    "32 MiB); free disk for --hours at the config's rates; the MQTT broker reachable (with TLS "
    "when configured); the leap-second table fresh; the installed systemd unit matching the "
    "installed software. When the daemon runs, its own live view follows (state, clock, "
    "devices, alarms).\n\n"
    "Exit status: 0 ready, 1 ready with warnings, 2 not ready.\n\n"
    "Example: mls doctor --config /etc/mls/vessel.yaml --hours 10"
)

MARK = {"ok": "[green] ok [/]", "warn": "[yellow]warn[/]", "fail": "[red]FAIL[/]", "skip": "[dim]skip[/]"}


def run_acquire_check(config: Path):
    """``mls acquire --config CONFIG --check``, in this process, its output captured."""
    import contextlib
    import io

    from acquire.doctor.configcheck import AcquireCheck
    from cli.commands.acquire_cmd import acquire

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            acquire(config=config, check=True, log_level="warning")
        except typer.Exit as e:
            code = e.exit_code
    return AcquireCheck(
        exit_code=code, errors=err.getvalue().splitlines(), output=out.getvalue().splitlines()
    )


def _print(report) -> None:
    from rich.console import Console
    from rich.markup import escape

    con = Console(highlight=False, soft_wrap=True)
    width = max(len(r.name + (f" {r.device}" if r.device else "")) for r in report.checks)
    for r in report.checks:
        label = r.name + (f" {r.device}" if r.device else "")
        con.print(f"{MARK[r.status.value]}  {label:<{width}}  {escape(r.message)}")
        if r.status.value in ("warn", "fail") and r.advice:
            con.print(f"      {'':<{width}}  [dim]→ {escape(r.advice)}[/]")
        for line in (r.data.get("errors") or [])[:-1] if r.name == "config" else []:
            con.print(f"      {'':<{width}}  {escape(line)}")
    if report.live is not None:
        _print_live(con, report.live)
    code = report.exit_code
    counts = report.as_dict()["counts"]
    verdict = {0: "[green]ready[/]", 1: f"[yellow]ready, {counts['warn']} warning(s)[/]"}.get(
        code, f"[red]not ready: {counts['fail']} check(s) failed[/]"
    )
    con.print(f"mls doctor: {verdict}")


def _print_live(con, live: dict) -> None:
    from rich.markup import escape

    if "error" in live:
        con.print(f"daemon (pid {live.get('pid')}): {escape(live['error'])}")
        return
    devices = ", ".join(f"{n} {s}" for n, s in live["devices"].items()) or "none"
    con.print(
        f"daemon running (pid {live['pid']}, {live['socket']}): {live['state']}, clock {live['clock']}, "
        f"devices: {escape(devices)}, log {live['log_free_mb']} MiB free, mqtt {live['mqtt']}"
    )
    for name, c in live["presurvey"].items():
        con.print(f"  {'ok  ' if c.get('ok') else 'not '} {name}: {escape(str(c.get('detail')))}")
    for a in live["alarms"]:
        con.print(f"  alarm {a['severity']} {a['name']} ({a['device']}): {escape(str(a['message']))}")


def doctor(
    config: Annotated[Path, vessel_config_option("Vessel config (YAML).")] = DEFAULT_CONFIG,
    as_json: Annotated[bool, json_option("Print the report as JSON (docs/doctor.md).")] = False,
    hours: Annotated[
        float, typer.Option("--hours", min=0.0, help="Hours of survey planned (disk check).")
    ] = 8.0,
    pps_wait_s: Annotated[
        float, typer.Option("--pps-wait", min=0.1, max=30.0, help="Seconds to wait for PPS pulses.")
    ] = 2.5,
) -> None:
    """``mls doctor`` (its help text is :data:`HELP`)."""
    import json

    from acquire import __version__
    from acquire.doctor.run import DoctorOptions, run_doctor

    opts = DoctorOptions(
        config=config,
        hours=hours,
        pps_wait_s=pps_wait_s,
        software_version=__version__,
        software_prefix=sys.prefix,
    )
    report = run_doctor(opts, run_acquire_check(config))
    if as_json:
        typer.echo(json.dumps(report.as_dict(), indent=2))
    else:
        _print(report)
    raise typer.Exit(report.exit_code)

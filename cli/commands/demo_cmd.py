"""``mls demo``: the end-to-end job on simulated devices (what ``make demo`` runs); the work is
:func:`office.jobs.demo.run_demo`."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.options import out_option, seed_option, set_option

if TYPE_CHECKING:
    from types import FrameType

    from rich.console import Console

    from office.jobs.demo import DemoError, DemoResult

EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130

HELP = (
    "The whole job on simulated devices, in about a minute and a half: simulated INS, profiler "
    "and PPS (the montreal scenario: two targets on a quay wall, six-fold line pattern on "
    "short lines), the acquisition daemon with its line guidance accepting the passes live, "
    "then mls export and mls calib run; prints the recovered boresight next to the truth.\n\n"
    "Everything goes to OUT (default ./demo-out, emptied of a previous demo's files first): "
    "run/ (the devices' run directory and the session), bundle/, calib/ (result.json, "
    "report.md, plots), logs/ (one log per step). Every child process runs in its own "
    "process group and is stopped when the demo ends, fails or is interrupted (Ctrl-C).\n\n"
    "Time runs at ×1: the daemon's clock model locks only on a PPS that ticks once per host "
    "second, and the guidance accepts a pass only with the clock LOCKED.\n\n"
    "Exit status: 0 when the calibration ran, 1 when a step failed (the message names it and "
    "its log), 130 on Ctrl-C (143 on SIGTERM, 129 on SIGHUP).\n\n"
    "Example: mls demo   (or: make demo)"
)


def demo(
    out: Annotated[
        Path,
        out_option(
            "Run directory (emptied of "
            "a previous demo's files; a non-empty directory of anything else "
            "is refused)."
        ),
    ] = Path("demo-out"),
    seed: Annotated[int, seed_option("Random seed of the simulation.")] = 0,
    line_m: Annotated[
        float,
        typer.Option(
            "--line-m",
            min=10.0,
            max=200.0,
            help="Length of lines 2–6 (m); each must hold its ~10 m capture window.",
        ),
    ] = 18.0,
    first_line_m: Annotated[
        float,
        typer.Option(
            "--first-line-m",
            min=30.0,
            max=300.0,
            help="Length of line 1 (m): the daemon starts and its clock locks before its capture window.",
        ),
    ] = 44.0,
    pass_gap_s: Annotated[
        float,
        typer.Option(
            "--pass-gap-s",
            min=2.0,
            max=120.0,
            help="Transit time from the end of a line to the start of the next.",
        ),
    ] = 3.0,
    set_: Annotated[
        list[str] | None,
        set_option("Further scenario override (repeatable), e.g. scanner.point_rate_scale=0.05."),
    ] = None,
) -> None:
    """``mls demo`` (its help text is :data:`HELP`)."""
    import signal
    import time

    from rich.console import Console

    from office.jobs.demo import DemoError, DemoSettings, Interrupted, run_demo

    console = Console(soft_wrap=True, emoji=False)  # long lines (paths) stay whole; ":100:" no emoji
    t0 = time.monotonic()
    settings = DemoSettings(
        out=out,
        seed=seed,
        first_line_m=first_line_m,
        line_m=line_m,
        pass_gap_s=pass_gap_s,
        extra_overrides=tuple(set_ or ()),
    )
    code = EXIT_OK
    with _stop_signals() as interrupted:
        try:
            res = run_demo(settings, console, interrupted)
        except DemoError as e:
            _print_failure(console, e, out)
            code = EXIT_FAILED
        except Interrupted as e:
            console.print(
                f"mls demo: interrupted ({e.signame}); every child process was stopped", highlight=False
            )
            code = EXIT_INTERRUPTED if e.signame == "SIGINT" else 128 + int(signal.Signals[e.signame])
        else:
            _print_result(console, res)
    console.print(f"wall time {time.monotonic() - t0:.1f} s", highlight=False)
    raise typer.Exit(code)


@contextmanager
def _stop_signals() -> Iterator[Callable[[], None]]:
    """Ctrl-C, SIGTERM and a closed terminal (SIGHUP) all stop the children before exiting:
    while the block runs they are only noted, and the callable it gets raises
    :class:`~office.jobs.demo.Interrupted` once one came; the previous handlers come back after."""
    import signal

    from office.jobs.demo import Interrupted

    pending: list[str] = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        pending.append(signal.Signals(signum).name)

    def interrupted() -> None:
        if pending:
            raise Interrupted(pending[0])

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        yield interrupted
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _print_failure(console: Console, e: DemoError, out: Path) -> None:
    """The step that failed, why, and where its log is."""
    from rich.markup import escape

    console.print(
        f"[bold red]mls demo failed[/bold red] at step [bold]{escape(e.step)}[/bold]: {escape(e.message)}",
        highlight=False,
    )
    if e.log is not None:
        console.print(f"  its log: {e.log}; all logs: {(out / 'logs').resolve()}", highlight=False)


def _print_result(console: Console, res: DemoResult) -> None:
    """The recovered boresight against the truth, the verdict, and where everything was written."""
    from rich.markup import escape

    from office.jobs.demo_compare import comparison_table

    console.print()
    console.print(comparison_table(res.rows))
    within = all(abs(r.error_sigmas) <= 3 for r in res.rows)
    console.print(
        (
            "[green]recovered within 3σ (realistic) of the truth on every angle[/green]"
            if within
            else "[bold red]NOT within 3σ (realistic) of the truth[/bold red]"
        )
        + f" · {res.accepted}/{res.n_passes} passes accepted live · "
        f"{sum(p['n_points'] for p in res.result.get('passes', []))} target points"
        + (f" and {len(res.result['tie_patches'])} tie patches" if res.result.get("tie_patches") else ""),
        highlight=False,
    )
    verdict = res.result.get("verdict", "none")
    console.print(
        f"verdict      {verdict}"
        + "".join(f"\n             · {escape(r)}" for r in res.result.get("verdict_reasons") or []),
        highlight=False,
    )
    console.print(f"result.json  {res.calib / 'result.json'}", highlight=False)
    console.print(f"report.md    {res.calib / 'report.md'}", highlight=False)
    for p in res.plots:
        console.print(f"plot         {p}", highlight=False)
    console.print(
        f"session      {res.session}\nbundle       {res.bundle}\nlogs         {res.out / 'logs'}",
        highlight=False,
    )

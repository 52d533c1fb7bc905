"""The one command-line interface, ``mls`` (docs/architecture.md §2; the console script ``mls = cli.app:main``).

Each command or command group lives in its own module ``cli/commands/<name>_cmd.py``
(:mod:`cli.commands`); this file only assembles them (``calib`` and ``sim`` are groups that
other command modules add to). A command module parses its options, calls the library
(``calib``, ``drivers``, ``acquire``, ``sim_devices``), prints and maps the outcome to an exit
status; it imports its heavy dependencies inside the command so that ``mls --help`` stays
fast.
"""

from __future__ import annotations

import typer

from cli.commands import (
    acquire_cmd,
    assess_cmd,  # noqa: F401  (adds calib c2c, history, compare)
    assess_run_cmd,  # noqa: F401  (adds calib assess)
    calib_cmd,
    checklist_cmd,
    decode_cmd,
    demo_cmd,
    design_cmd,
    export_cmd,
    logs_cmd,
    plan_cmd,
    run_cmd,  # noqa: F401  (adds calib run)
    sim_cmd,
    sim_devices_cmd,  # noqa: F401  (adds sim devices, sim replay)
    status_cmd,
)

app = typer.Typer(
    name="mls",
    help=(
        "marine-mls: acquisition, synchronization and boresight calibration for a marine "
        "mobile LiDAR system (iXblue Hydrins INS + Z+F Profiler 9012)."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

app.add_typer(calib_cmd.app, name="calib")
app.command("decode")(decode_cmd.decode)
app.command("demo", help=demo_cmd.HELP)(demo_cmd.demo)
app.add_typer(sim_cmd.app, name="sim")
app.add_typer(logs_cmd.app, name="logs")
app.command("status")(status_cmd.status)
app.command("acquire", help=acquire_cmd.HELP)(acquire_cmd.acquire)
app.command("export", help=export_cmd.HELP)(export_cmd.export)
app.command("plan", help=plan_cmd.HELP)(plan_cmd.plan)
app.command("checklist", help=checklist_cmd.HELP)(checklist_cmd.checklist)
app.command("design", help=design_cmd.HELP)(design_cmd.design)


@app.command("version")
def version() -> None:
    """Print the software version."""
    from acquire import __version__

    typer.echo(__version__)


def main() -> None:  # console entry point
    app()


if __name__ == "__main__":
    main()

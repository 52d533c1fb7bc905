"""The one command-line interface, ``mls`` (docs/architecture.md §2; the console script ``mls = cli.app:main``).

Each command or command group lives in its own module ``cli/commands/<name>_cmd.py``
(:mod:`cli.commands`); this file only assembles them (``calib`` and ``sim`` are groups that
other command modules add to). A command module parses its options, calls the library
(``calib``, ``drivers``, ``acquire``, ``sim_devices``), prints and maps the outcome to an exit
status; it imports its heavy dependencies inside the command so that ``mls --help`` stays
fast.

Errors (docs/architecture.md §9.3): an :class:`~calib.core.errors.MlsError` that escapes a
command is caught once, here, by :class:`MlsGroup`: one line ``error: <message>`` on stderr and
exit status :data:`EXIT_ERROR`. A command catches ``MlsError`` itself only where it needs its own
exit status or message (``mls acquire``: 2 invalid config, 1 cannot start).
"""

from __future__ import annotations

import typer
from typer.core import TyperGroup

from calib.core.errors import MlsError
from calib.io.dirlock import release_held
from cli.commands import (
    acquire_cmd,
    assess_cmd,  # noqa: F401  (adds calib c2c, history, compare)
    assess_run_cmd,  # noqa: F401  (adds calib assess)
    calib_cmd,
    decode_cmd,
    demo_cmd,
    design_cmd,
    doctor_cmd,
    logs_cmd,
    operator_cmd,
    plan_cmd,
    run_cmd,  # noqa: F401  (adds calib run)
    sim_cmd,
    sim_devices_cmd,  # noqa: F401  (adds sim devices, sim replay)
)
from cli.commands.survey import export_cmd, georef_cmd, watch_cmd

#: Exit status of an :class:`MlsError` that no command handles itself.
EXIT_ERROR = 1


class MlsGroup(TyperGroup):
    """The ``mls`` group: every command (and sub-group) runs inside :meth:`invoke`, so an
    :class:`MlsError` escaping any of them ends the run with its message on one line of stderr,
    never a traceback, under the console script and ``typer.testing.CliRunner`` alike."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except MlsError as e:
            typer.echo(f"{typer.style('error:', fg=typer.colors.RED)} {e}", err=True)
            raise typer.Exit(EXIT_ERROR) from None
        finally:
            release_held()  # the output directories the command held (calib/io/dirlock.py)


app = typer.Typer(
    cls=MlsGroup,
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
app.command("status")(operator_cmd.status)
app.command("acquire", help=acquire_cmd.HELP)(acquire_cmd.acquire)
app.command("export", help=export_cmd.HELP)(export_cmd.export)
app.command("georef", help=georef_cmd.HELP)(georef_cmd.georef)
app.command("watch", help=watch_cmd.HELP)(watch_cmd.watch)
app.command("plan", help=plan_cmd.HELP)(plan_cmd.plan)
app.command("checklist", help=operator_cmd.CHECKLIST_HELP)(operator_cmd.checklist)
app.command("design", help=design_cmd.HELP)(design_cmd.design)
app.command("doctor", help=doctor_cmd.HELP)(doctor_cmd.doctor)


@app.command("version")
def version() -> None:
    """Print the software version."""
    from acquire import __version__

    typer.echo(__version__)


def main() -> None:
    """The console entry point; :class:`MlsGroup` reports an :class:`MlsError` of any command."""
    app()


if __name__ == "__main__":
    main()

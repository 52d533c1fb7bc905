"""The options and arguments that several ``mls`` commands share, declared once in typer's
``Annotated`` style, so that a flag is spelled, bounded and explained the same in every command.

Two kinds:

- a type, where the commands mean one thing by the option: ``las: Las = False``;
- a function of the command's own help, where the flag and its bounds are shared but what it
  names is the command's (``--out`` is a bundle, a directory of tiles, a GeoJSON file):
  ``out: Annotated[Path, out_option("Directory of the tiles (created).")]``.

The default is the parameter's (none: required). A repeatable option (``--set``) is a
``list[str] | None`` that defaults to None: typer passes the command None when it is not given,
else the list.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer


def _option(*decls: str, **settings: Any) -> Callable[[str], Any]:
    """A shared flag (its names, metavar and bounds); each command gives its help."""

    def option(help: str) -> Any:
        return typer.Option(*decls, help=help, **settings)

    option.__doc__ = f"The {decls[0]} option with the command's help."
    return option


# -- shared flags, the help each command's own ------------------------------------------------

#: an output file or directory (what it holds is the command's)
out_option = _option("--out", "-o")
#: write into an output that already holds files
force_option = _option("--force")
#: the random seed of a simulation
seed_option = _option("--seed")
#: scenario overrides by dotted key (repeatable)
set_option = _option("--set", metavar="KEY=VALUE")
#: a scenario by name (montreal, montreal_piles, harbour_cal, terrestrial, tower) or YAML file
scenario_option = _option("--scenario", "-s", metavar="NAME|PATH")
#: print JSON instead of tables
json_option = _option("--json")
#: the vessel config (YAML) of the daemon
vessel_config_option = _option("--config", "-c")
#: the daemon's status socket
socket_option = _option("--socket")
#: neighbours of a local least-squares plane (CloudCompare's '-MODEL LS KNN k')
knn_option = _option("--knn", min=3)
#: the output CRS of georeferenced points
crs_option = _option("--crs")
#: drop points the trajectory does not cover instead of stopping
skip_uncovered_option = _option("--skip-uncovered")
# mls sim devices and mls sim replay
speed_option = _option("--speed", min=0.01, max=100.0)
run_dir_option = _option("--run-dir")
write_config_option = _option("--write-config", metavar="vessel.yaml")
profiler_host_option = _option("--profiler-host")
can_port_option = _option("--can-port", min=1, max=65535)
realtime_option = _option("--realtime")


def session_argument(help: str) -> Any:
    """A recorded session directory (``YYYYmmddTHHMMSSZ_<vessel>``), with the command's help."""
    return typer.Argument(help=help)


def bundle_argument(help: str, metavar: str = "BUNDLE") -> Any:
    """A calibration bundle directory, with the command's help."""
    return typer.Argument(metavar=metavar, help=help)


# -- shared options, one meaning -------------------------------------------------------------

Force = Annotated[
    bool, force_option("Write into an --out directory that already holds files (same names replaced).")
]
HistoryDb = Annotated[
    Path | None,
    typer.Option(
        "--db",
        help="History database (default: $MLS_HISTORY_DB, else ~/.local/share/marine-mls/history.sqlite).",
    ),
]
SessionDir = Annotated[Path, session_argument("Session directory (YYYYmmddTHHMMSSZ_<vessel>).")]
#: what the survey commands (mls georef, mls watch) read
SurveySource = Annotated[
    Path, typer.Argument(help="A session directory (seg-*.mcap) or a calibration bundle.")
]
Calibration = Annotated[
    str | None,
    typer.Option(
        "--calibration", "-c", metavar="RESULT|#ID", help="result.json (file or directory) or history id."
    ),
]
Las = Annotated[bool, typer.Option("--las", help="Write uncompressed .las instead of .laz.")]
PointRateScale = Annotated[
    float | None,
    typer.Option(
        "--point-rate-scale",
        min=1e-6,
        max=1.0,
        help="Scale the profiler's point rate (1 = the full Z+F rate); overrides the scenario.",
    ),
]
InsProtocol = Annotated[
    str, typer.Option("--ins-protocol", help="INS output: nmea (PHINS standard + ZDA) or stdbin.")
]
InsRate = Annotated[float, typer.Option("--ins-rate", min=1.0, max=200.0, help="INS output rate (Hz).")]
ProfilerPort = Annotated[
    int, typer.Option("--profiler-port", min=0, max=65535, help="Profiler UDP port (0: a free one).")
]
PpsPort = Annotated[int, typer.Option("--pps-port", min=0, max=65535, help="PPS UDP port (0: a free one).")]
CanChannel = Annotated[str, typer.Option("--can-channel", help="CAN udp_multicast group.")]

"""``mls calib c2c``, ``mls calib history``, ``mls calib compare``: relative accuracy and
repeatability (thesis §4.4.6, §4.5.4, §4.5.5; docs/architecture.md §7 "Assessment").

The commands are added to the ``mls calib`` group of :mod:`cli.commands.calib_cmd`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from cli.commands.calib_cmd import app
from cli.options import HistoryDb, knn_option

if TYPE_CHECKING:
    from rich.table import Table

    from calib.assess.c2c import C2CResult


def _fail(message: str) -> NoReturn:
    """One line ``error: <message>`` on stderr and exit status 2 (these commands' own status for
    bad input; an uncaught MlsError would give :data:`cli.app.EXIT_ERROR`)."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    raise typer.Exit(2)


def _vector(text: str, option: str) -> list[float]:
    try:
        v = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        v = []
    if len(v) != 3:
        _fail(f"{option} {text!r}: expected three comma-separated numbers X,Y,Z")
    return v


def _mm(x: float) -> str:
    return f"{x * 1000.0:.2f}"


@dataclass(frozen=True)
class _Orientation:
    """How ``--signed`` orients the local normals: along a direction or toward a point (or
    neither when the distances are unsigned)."""

    direction: list[float] | None = None
    toward_m: list[float] | None = None


def _orientation(signed: bool, toward_direction: str | None, toward_point: str | None) -> _Orientation:
    """The orientation of the normals that the options ask for; exit 2 on a contradiction."""
    if (toward_direction or toward_point) and not signed:
        _fail("--toward-direction/--toward-point only apply with --signed")
    if toward_direction and toward_point:
        _fail("give --toward-direction or --toward-point, not both")
    if not signed:
        return _Orientation()
    if toward_point:
        return _Orientation(toward_m=_vector(toward_point, "--toward-point"))
    return _Orientation(direction=_vector(toward_direction or "0,0,1", "--toward-direction"))


def _run_c2c(
    compared: Path,
    reference: Path,
    knn: int,
    orient: _Orientation,
    out: Path | None,
    max_dist: float | None,
    collinear_tol: float,
    workers: int,
) -> C2CResult:
    """Read both clouds, compute the distances (a progress bar on stderr), write ``--out``."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from calib.assess.c2c import c2c
    from calib.core.errors import MlsError
    from calib.io.cloudio import read_cloud, write_cloud

    err = Console(stderr=True, emoji=False)  # ":100:" of file:line:column is no emoji
    try:
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%"),
            TimeElapsedColumn(),
            console=err,
            transient=True,
        ) as progress:
            t = progress.add_task("reading clouds", total=2)
            cmp_cloud = read_cloud(compared)
            progress.advance(t)
            ref_cloud = read_cloud(reference)
            progress.advance(t)
            t = progress.add_task(
                f"C2C ({len(cmp_cloud):,} → {len(ref_cloud):,} points)", total=len(cmp_cloud)
            )
            result = c2c(
                cmp_cloud.xyz_m,
                ref_cloud.xyz_m,
                knn,
                max_distance_m=max_dist,
                collinear_tol=collinear_tol,
                workers=workers,
                progress=lambda done, total: progress.update(t, completed=done),
                orient_direction=orient.direction,
                orient_toward_m=orient.toward_m,
            )
            if out is not None:
                progress.add_task(f"writing {out}", total=None)
                write_cloud(out, cmp_cloud, result.extra_dimensions())
    except MlsError as e:
        _fail(str(e))
    return result


def _c2c_table(result: C2CResult, compared: Path, reference: Path, knn: int, signed: bool) -> Table:
    """The statistics of the distances (mm): local plane, signed, nearest neighbour."""
    from rich.table import Table

    table = Table(title=f"C2C distances of {compared.name} to {reference.name} (mm)")
    for col in ("", "count", "mean", "median", "RMS", "std", "p95 |d|", "max |d|"):
        table.add_column(col, justify="left" if not col else "right")
    rows = [(f"local plane, k={knn}", result.stats())]
    if signed:
        rows.append(("signed", result.stats(signed=True)))
    rows.append(("nearest neighbour", result.nn_stats()))
    for name, s in rows:
        table.add_row(
            name,
            f"{s.count:,}",
            _mm(s.mean_m),
            _mm(s.median_m),
            _mm(s.rms_m),
            _mm(s.std_m),
            _mm(s.p95_m),
            _mm(s.max_m),
        )
    return table


def _c2c_notes(result: C2CResult, max_dist: float | None, out: Path | None) -> list[str]:
    """The lines under the table: fallbacks, points beyond --max-dist, ambiguous signs, output."""
    notes = []
    if result.n_fallback:
        notes.append(
            f"{result.n_fallback:,} points without a plane (fewer than 3 or collinear "
            f"neighbours): nearest-neighbour distance used"
        )
    beyond = len(result) - int(result.within_max.sum())
    if beyond:
        assert max_dist is not None  # points are beyond only a given --max-dist
        notes.append(f"{beyond:,} points beyond --max-dist {max_dist:g} m: not in the statistics")
    if result.n_ambiguous_sign:
        notes.append(
            f"{result.n_ambiguous_sign:,} signed distances have an ambiguous sign (local "
            f"normal nearly perpendicular to the orientation)"
        )
    if out is not None:
        notes.append(f"distances written to {out}")
    return notes


@app.command("c2c")
def c2c_cmd(
    compared: Annotated[
        Path,
        typer.Argument(
            help="Compared cloud (LAS/LAZ, or ASCII 'x y z' per line): every point of it gets a distance."
        ),
    ],
    reference: Annotated[Path, typer.Argument(help="Reference cloud the local planes are fitted to.")],
    knn: Annotated[
        int,
        knn_option(
            "Neighbours of the nearest reference point "
            "in each local least-squares plane (CloudCompare's '-MODEL LS KNN k')."
        ),
    ] = 6,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Write the compared cloud with its "
            "distances: .las/.laz get the extra dimension "
            "'c2c_distance_m' (and 'c2c_signed_distance_m' with "
            "--signed); any other suffix is ASCII with the distance "
            "columns appended.",
        ),
    ] = None,
    signed: Annotated[
        bool,
        typer.Option(
            "--signed",
            help="Also compute signed distances, the "
            "local normals oriented along --toward-direction (default 0,0,1: "
            "up in a z-up cloud) or toward --toward-point.",
        ),
    ] = False,
    toward_direction: Annotated[
        str | None,
        typer.Option(
            "--toward-direction", metavar="DX,DY,DZ", help="Orientation of the normals for --signed."
        ),
    ] = None,
    toward_point: Annotated[
        str | None,
        typer.Option(
            "--toward-point",
            metavar="X,Y,Z",
            help="Orient the normals for --signed toward this "
            "point (e.g. the scanner's position: positive = in "
            "front of the reference surface).",
        ),
    ] = None,
    max_dist: Annotated[
        float | None,
        typer.Option(
            "--max-dist",
            min=0.0,
            help="Maximum search "
            "distance (m; CloudCompare's -MAX_DIST): farther "
            "points get this value and are left out of the "
            "statistics.",
        ),
    ] = None,
    collinear_tol: Annotated[
        float,
        typer.Option(
            "--collinear-tol",
            min=0.0,
            max=0.99,
            help="A "
            "neighbourhood narrower than this fraction of its length "
            "is a line: no plane, the nearest-neighbour distance is "
            "used. Raise it (e.g. 0.05) for single scan lines.",
        ),
    ] = 1e-5,
    workers: Annotated[
        int, typer.Option("--workers", help="Threads for the KD-tree queries (-1: all cores).")
    ] = 1,
) -> None:
    """Cloud-to-cloud distances to local least-squares planes (CloudCompare's C2C).

    Same semantics as CloudCompare's '-C2C_DIST -MODEL LS KNN k'.
    """
    from rich.console import Console

    orient = _orientation(signed, toward_direction, toward_point)
    result = _run_c2c(compared, reference, knn, orient, out, max_dist, collinear_tol, workers)
    console = Console()
    console.print(_c2c_table(result, compared, reference, knn, signed))
    for n in _c2c_notes(result, max_dist, out):
        console.print(n)


# -- history --------------------------------------------------------------------------------


@app.command("history")
def history_cmd(
    vessel: str | None = typer.Option(None, "--vessel", help="Only this vessel's calibrations."),
    mount: str | None = typer.Option(None, "--mount", help="Only this mount id."),
    db: HistoryDb = None,
) -> None:
    """List the recorded boresight calibrations, oldest survey first."""
    from rich.console import Console
    from rich.table import Table

    from calib.assess.history import ANGLES, default_db_path, list_results, validate_result
    from calib.core.errors import MlsError

    try:
        records = list_results(vessel, db=db, mount_id=mount)
    except MlsError as e:
        _fail(str(e))
    console = Console()
    where = db if db is not None else default_db_path()
    if not records:
        console.print(f"no calibrations recorded in {where}" + (f" for vessel {vessel!r}" if vessel else ""))
        return
    table = Table(title=f"Calibration history ({where})")
    for col in (
        "id",
        "survey (UTC)",
        "vessel",
        "mount",
        "roll ± σ (°)",
        "pitch ± σ (°)",
        "yaw ± σ (°)",
        "σ",
        "verdict",
        "σ̂0²",
        "points",
        "bundle",
        "version",
    ):
        table.add_column(col, justify="right" if col in ("id", "σ̂0²", "points") else "left")
    for r in records:
        v = validate_result(r.result, r.label)
        real = v["sigma_realistic_deg"]
        sig, kind = (real, "realistic") if real is not None else (v["sigma_scaled_deg"], "scaled")
        cells = [f"{v['boresight_deg'][a]:.4f} ± {sig[a]:.4f}" for a in ANGLES]
        table.add_row(
            str(r.id),
            r.date_utc[:16].replace("T", " "),
            r.vessel,
            r.mount_id,
            *cells,
            kind,
            r.verdict or "—",
            f"{r.sigma0_squared:.3g}",
            f"{r.n_points:,}",
            r.bundle_fingerprint[:10],
            r.software_version,
        )
    console.print(table)


@app.command("compare")
def compare_cmd(
    a: str = typer.Argument(..., help="First calibration: a history id or a result.json path."),
    b: str = typer.Argument(..., help="Second calibration: a history id or a result.json path."),
    k_sigma: float = typer.Option(3.0, "--k", min=0.1, help="Flag a change beyond k times the combined σ."),
    db: HistoryDb = None,
) -> None:
    """Has the mount moved? Test two calibrations against their combined σ.

    Uses each result's realistic σ when it has one, else its scaled σ.
    """
    from rich.console import Console
    from rich.table import Table

    from calib.assess.history import compare, resolve_result
    from calib.core.errors import MlsError

    try:
        ra, la = resolve_result(a, db, "A")
        rb, lb = resolve_result(b, db, "B")
        cmp = compare(ra, rb, k_sigma, a_label=la, b_label=lb)
    except MlsError as e:
        _fail(str(e))
    table = Table(title=f"A = {cmp.a_label}, B = {cmp.b_label}")
    for col in (
        "angle",
        "A (°)",
        "B (°)",
        "B − A (°)",
        f"σA {cmp.sigma_kind_a} (°)",
        f"σB {cmp.sigma_kind_b} (°)",
        "combined σ (°)",
        "|Δ|/σ",
        "",
    ):
        table.add_column(col, justify="left" if col in ("angle", "") else "right")
    for c in cmp.angles:
        table.add_row(
            c.angle,
            f"{c.a_deg:.4f}",
            f"{c.b_deg:.4f}",
            f"{c.difference_deg:+.4f}",
            f"{c.sigma_a_deg:.4f}",
            f"{c.sigma_b_deg:.4f}",
            f"{c.sigma_combined_deg:.4f}",
            f"{c.n_sigma:.1f}",
            "CHANGED" if c.changed else "ok",
        )
    console = Console()
    console.print(table)
    console.print(cmp.message)

"""``mls calib assess``: relative accuracy of a calibration, before and after (thesis §4.4.6,
§4.5.4; docs/architecture.md §7 "Assessment"). Added to the ``mls calib`` group of
:mod:`cli.commands.calib_cmd`; the work is :mod:`calib.assess.comparison`, the report
:mod:`calib.assess.summary`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.commands.calib_cmd import app
from cli.options import Force, bundle_argument, knn_option, out_option

if TYPE_CHECKING:
    from rich.table import Table

    from calib.assess.results import Assessment, AssessOptions

ASSESS_HELP = (
    "Relative accuracy: compare reciprocal passes before and after a calibration.\n\n"
    "The same returns of two passes (the reciprocal pairs 0°/180°, 45°/225°, … found from the "
    "sailed headings, or --pairs) are georeferenced with the a-priori mount of site.yaml "
    "(before) and with the result's boresight (after), and compared with CloudCompare-style "
    "cloud-to-cloud distances to local least-squares planes, on the site's validation planes "
    "(or planar patches found in both passes when the site lists none) and on the whole "
    "overlap. Prints the tables, writes assessment.md (the improvement in words), "
    "assessment.json and PNG figures (histograms per surface, distance against height) into "
    "--out. A simulated bundle (truth.json) is also compared with the truth.\n\n"
    "Example: mls calib assess sim/tower --result out/result.json --out out/assess"
)


def _mm(x_m) -> str:
    """Millimetres for the tables: 1384, 13, 4.6, 0.41."""
    if x_m is None or x_m != x_m:
        return "—"
    mm = x_m * 1e3
    return f"{mm:.0f}" if abs(mm) >= 10 else f"{mm:.1f}" if abs(mm) >= 1 else f"{mm:.2f}"


@app.command("assess", help=ASSESS_HELP)
def assess_cmd(
    bundle: Annotated[
        Path,
        bundle_argument(
            "Calibration bundle directory (site.yaml, trajectory, points; truth.json when simulated)."
        ),
    ],
    result: Annotated[
        Path,
        typer.Option(
            "--result",
            "-r",
            help="Calibration result (result.json, or the directory holding it) whose boresight is assessed.",
        ),
    ],
    out: Annotated[
        Path,
        out_option(
            "Output directory (created) for assessment.md, assessment.json and the figures; "
            "one that holds files is refused unless --force."
        ),
    ],
    force: Force = False,
    pairs: Annotated[
        str | None,
        typer.Option(
            "--pairs",
            metavar="A:B[,C:D]",
            help="Pass pairs to compare, compared pass first (e.g. 1:2,5:6); default: the reciprocal pairs.",
        ),
    ] = None,
    knn: Annotated[
        int,
        knn_option(
            "Neighbours of each local least-squares "
            "plane (CloudCompare's '-MODEL LS KNN k'). On sparse scan lines "
            "6 neighbours can be collinear; the run says so: then try 12."
        ),
    ] = 6,
    gate_m: Annotated[
        float,
        typer.Option(
            "--gate",
            min=0.001,
            help="Returns within this distance "
            "(m) of a validation plane belong to it (after the "
            "calibration; then trimmed per pass to its own plane).",
        ),
    ] = 1.0,
    auto_planes: Annotated[
        bool,
        typer.Option(
            "--auto-planes",
            help="Find planar patches seen by both passes even when site.yaml lists validation planes.",
        ),
    ] = False,
    scanner_height_m: Annotated[
        float,
        typer.Option(
            "--scanner-height",
            help="Height of the scanner above the water line (m); heights are reported above the water.",
        ),
    ] = 0.0,
    overlap: Annotated[
        bool, typer.Option("--overlap/--no-overlap", help="Also compare the whole overlap of each pair.")
    ] = True,
) -> None:
    """``mls calib assess`` (its help text is :data:`ASSESS_HELP`)."""
    from rich.console import Console

    from calib.assess.pairs import parse_pairs
    from calib.assess.results import AssessError, AssessOptions
    from calib.assess.summary import summary_lines
    from calib.io.outputs import hold_output_dir

    hold_output_dir(out, "--out", force)  # before the assessment (an MlsError: one line, status 1)
    try:
        pair_list = parse_pairs(pairs) if pairs else None
    except AssessError as e:
        raise typer.BadParameter(str(e), param_hint="--pairs") from None
    # an MlsError (bad bundle, result or pair) ends the command in cli.app: one line, exit status 1
    options = AssessOptions(
        k=knn, gate_m=gate_m, auto_planes=auto_planes, scanner_height_m=scanner_height_m, overlap=overlap
    )
    a, written = _assess_and_write(bundle, result, pair_list, options, out)

    console = Console()
    for note in a.notes:
        console.print(f"note: {note}", highlight=False)
    for line in summary_lines(a):
        console.print(line, highlight=False)
    tables = [t for pair in a.pairs if (t := _pair_table(a, pair, knn)) is not None]
    if a.height_fits:
        tables.append(_height_table(a))
    if tables:
        tables[
            -1
        ].caption = (
            f"wrote {written['markdown'][0]}, {written['json'][0].name} and {len(written['figures'])} figures"
        )
    for table in tables:
        console.print(table)
    if not tables:
        console.print(f"nothing compared; wrote {written['markdown'][0]}", highlight=False)


def _assess_and_write(
    bundle: Path,
    result: Path,
    pair_list: list[tuple[int, int]] | None,
    options: AssessOptions,
    out: Path,
) -> tuple[Assessment, dict[str, list[Path]]]:
    """Assess the result's boresight on the bundle and write the report into ``out``, a spinner
    on stderr saying which step runs; the assessment and the files written."""
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from calib.assess.comparison import assess
    from calib.assess.history import load_result
    from calib.assess.summary import write_assessment

    err = Console(stderr=True, emoji=False)  # ":100:" of file:line:column is no emoji
    doc = load_result(result)
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    ) as progress:
        task = progress.add_task("assessing", total=None)
        a = assess(
            bundle, doc, pair_list, options, progress=lambda msg: progress.update(task, description=msg)
        )
        progress.update(task, description="writing figures and assessment.md")
        written = write_assessment(a, out)
    return a, written


def _pair_table(a: Assessment, pair: tuple[int, int], knn: int) -> Table | None:
    """The median C2C of one pair of passes per surface, before and after (None: nothing compared)."""
    from rich.table import Table

    from calib.assess.summary import fmt_ratio

    rows = sorted(
        (c for c in a.comparisons if c.pair == pair), key=lambda c: (c.source == "overlap", -c.height_m)
    )
    if not rows:
        return None
    truth = a.truth_boresight_deg is not None
    h = a.headings_deg
    table = Table(
        title=f"passes {pair[0]} ({h[pair[0]]:.0f}°) ↔ {pair[1]} ({h[pair[1]]:.0f}°): "
        f"median C2C (mm), local LS planes k = {knn}"
    )
    cols = ["surface", "height m", "returns", "before", "after", "×", "expected", "95 %", "floor"] + (
        ["true mount"] if truth else []
    )
    for col in cols:
        table.add_column(col, justify="left" if col == "surface" else "right", no_wrap=True)
    for c in rows:
        cells = [
            c.name if c.source != "overlap" else "overlap",
            f"{c.height_m:.1f}",
            f"{c.after.count:,}",
            _mm(c.before.median_m),
            _mm(c.after.median_m),
            fmt_ratio(c.improvement),
            _mm(c.expected_median_m),
            _mm(c.expected_upper_m),
            _mm(c.floor_median_m),
        ]
        if truth:
            cells.append(_mm(c.true_mount.median_m if c.true_mount else None))
        table.add_row(*cells)
    return table


def _height_table(a: Assessment) -> Table:
    """The slope of C2C against height above the water, per pair, before and after."""
    from rich.table import Table

    table = Table(title="C2C against height above the water (least-squares line)")
    for col in ("passes", "before (mm per m)", "after (mm per m)", "heights"):
        table.add_column(col, justify="left" if col == "passes" else "right")
    for pair in a.pairs:
        try:
            b, f = a.height_fit(pair, "before"), a.height_fit(pair, "after")
        except KeyError:
            continue
        table.add_row(
            f"{pair[0]}:{pair[1]}",
            f"{b.slope_m_per_m * 1e3:.1f}",
            f"{f.slope_m_per_m * 1e3:.1f}",
            f"{b.height_span_m[0]:.0f}–{b.height_span_m[1]:.0f} m",
        )
    return table

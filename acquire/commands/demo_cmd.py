"""``mls demo``: the most complete job that runs without hardware (what ``make demo`` runs)."""

from __future__ import annotations

from pathlib import Path

import typer

#: The small example bundle shipped with the sources (see examples/make_example_bundle.py).
EXAMPLE_BUNDLE = Path(__file__).resolve().parents[2] / "examples" / "montreal-mini"


HELP = (
    "Georeference the example bundle (examples/montreal-mini) and say where the LAZ files "
    "went.\n\n"
    "Two passes past a quay with two calibration targets, georeferenced with the example's true "
    "boresight (from its truth.json) into one LAZ per pass in the UTM zone.\n\n"
    "For now this is the most complete job that runs without hardware; the end-to-end demo "
    "(simulated devices → acquisition → calibration → report) replaces it in a later issue."
)


def demo(
    out: Path = typer.Option(Path("demo-out"), "--out", "-o",
                             help="Output directory; the LAZ files go to OUT/laz/."),  # fmt: skip
) -> None:
    """``mls demo`` (its help text is :data:`HELP`)."""
    from rich.console import Console
    from rich.markup import escape

    from acquire.commands.calib_cmd import run_georef
    from calib.bundle import BundleError, read_truth

    console = Console()
    if not (EXAMPLE_BUNDLE / "site.yaml").is_file():
        console.print(f"[red]error:[/red] the example bundle is missing: {EXAMPLE_BUNDLE} "
                      f"(run examples/make_example_bundle.py)", highlight=False)  # fmt: skip
        raise typer.Exit(1)
    try:
        b = read_truth(EXAMPLE_BUNDLE)["boresight_deg"]
        boresight_deg = (float(b["roll"]), float(b["pitch"]), float(b["yaw"]))
    except (BundleError, KeyError, TypeError, ValueError) as e:
        console.print(f"[red]error:[/red] {EXAMPLE_BUNDLE}/truth.json: {escape(str(e))}",
                      highlight=False)  # fmt: skip
        raise typer.Exit(1) from None
    laz_dir = out / "laz"
    console.print(f"[bold]mls demo[/bold]: georeferencing {EXAMPLE_BUNDLE}", highlight=False)
    outputs = run_georef(EXAMPLE_BUNDLE, laz_dir, boresight_deg=boresight_deg,
                         boresight_source="the example's truth.json")
    console.print(f"\nLAZ files ({len(outputs)} passes) are in [bold]{laz_dir.resolve()}[/bold]:",
                  highlight=False)  # fmt: skip
    for o in outputs:
        console.print(f"  {o.path.resolve()}", highlight=False)

"""``mls sim``: simulators. ``dataset`` writes a simulated calibration bundle (docs/architecture.md §4) with
its ``truth.json``; the device emulators (``devices``) and the replay (``replay``) join this
group from their own modules."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer

from cli.options import (
    InsProtocol,
    InsRate,
    PointRateScale,
    force_option,
    out_option,
    scenario_option,
    seed_option,
    set_option,
)

app = typer.Typer(
    help="Simulators: calibration datasets, device emulators, replays.",
    no_args_is_help=True,
)


@contextmanager
def simulation_bar(console, description: str):
    """The transient bar under which a command simulates, titled ``description``: yields ``(bar, task, progress)``, with
    ``progress`` the callback ``simulate`` reports to."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(description, total=None)
        yield bar, task, lambda done, total: bar.update(task, completed=done, total=total)


@app.command("dataset")
def dataset(
    scenario: Annotated[
        str,
        scenario_option(
            "A shipped scenario (montreal, montreal_piles, harbour_cal, terrestrial, tower), random (a geometry "
            "drawn from --seed; the draw lands in truth.json) or a scenario YAML file."
        ),
    ],
    out: Annotated[Path, out_option("Bundle directory to write (created).")],
    force: Annotated[
        bool, force_option("Write into an --out directory that already holds files (bundle files replaced).")
    ] = False,
    seed: Annotated[int, seed_option("Random seed: the same seed gives the same bytes.")] = 0,
    point_rate_scale: PointRateScale = None,
    set_: Annotated[
        list[str] | None,
        set_option(
            "Override a scenario value by dotted key, e.g. --set noise.pos.model=white "
            "--set truth.boresight_deg=[0.2,1.2,0.15] (repeatable; values are YAML)."
        ),
    ] = None,
    compress: Annotated[
        bool, typer.Option("--gzip", help="Write points.csv.gz instead of points.csv.")
    ] = False,
) -> None:
    """Simulate a calibration bundle with its truth.json.

    The vessel sails the scenario's passes around its targets with the injected systematic
    errors; the bundle holds site.yaml (the a-priori mount), trajectory.csv (with POS errors
    and sigmas) and points.csv (raw range and scan angle), as docs/architecture.md §4 describes.
    An --out directory that already holds files is refused unless --force."""
    import math
    import time

    from rich import box
    from rich.console import Console
    from rich.table import Table

    from calib.core.errors import MlsError
    from calib.io.outputs import hold_output_dir
    from calib.sim.simulate import simulate

    console = Console(emoji=False)  # ":100:" of file:line:column is no emoji
    overrides = list(set_ or ())
    if point_rate_scale is not None:
        overrides.append(f"scanner.point_rate_scale={point_rate_scale!r}")
    t0 = time.perf_counter()
    try:
        hold_output_dir(out, "--out", force)  # before simulating; held to the end
        with simulation_bar(console, f"simulating {scenario}") as (bar, task, progress):
            result = simulate(scenario, seed, overrides=overrides, progress=progress)
            bar.update(task, description="writing the bundle")
            path = result.write(out, compress_points=compress)
    except (MlsError, OSError) as e:
        from rich.markup import escape

        console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)  # one line
        raise typer.Exit(2) from None
    elapsed = time.perf_counter() - t0

    counts = result.point_counts()
    names = list(next(iter(counts.values())))
    table = Table(
        title=f"{result.scenario.name}, seed {seed}: returns per pass and surface",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        collapse_padding=True,
    )
    for col in ("pass", "hdg", *("other" if n == "background" else n for n in names), "total"):
        table.add_column(col, justify="right", no_wrap=True)
    for p in result.plan.passes:
        row = counts[p.id]
        table.add_row(
            str(p.id),
            f"{math.degrees(p.relative_heading_rad):g}°",
            *(str(row[n]) for n in names),
            str(sum(row.values())),
        )
    totals = {n: sum(c[n] for c in counts.values()) for n in names}
    table.add_row("all", "", *(str(totals[n]) for n in names), str(sum(totals.values())), style="bold")
    console.print(table)
    size = sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    b = result.truth["boresight_deg"]
    console.print(
        f"wrote {path} ({size / 1e6:.1f} MB) in {elapsed:.1f} s; true boresight roll "
        f"{b['roll']:.4f}°, pitch {b['pitch']:.4f}°, yaw {b['yaw']:.4f}° (truth.json)",
        highlight=False,
    )


@app.command("session")
def session(
    out: Annotated[
        Path, out_option("Directory the session directory is created in (the daemon's session directory).")
    ],
    scenario: Annotated[
        str,
        scenario_option(
            "A shipped scenario (montreal, montreal_piles, harbour_cal, terrestrial, tower) or a scenario YAML file."
        ),
    ] = "montreal",
    minutes: Annotated[
        float, typer.Option("--minutes", "-m", min=0.01, help="Length of the session (minutes).")
    ] = 1.0,
    rate_scale: Annotated[
        float,
        typer.Option(
            "--rate-scale",
            min=1e-4,
            max=1.0,
            help="Fraction of the full Z+F point rate (1 M points/s): profile rate and points per 360° "
            "each × √F, as the simulator scales them.",
        ),
    ] = 1.0,
    seed: Annotated[int, seed_option("Random seed: the same seed gives the same records.")] = 0,
    force: Annotated[
        bool, force_option("Replace a session of the same name (the scenario's vessel and start) in --out.")
    ] = False,
    ins_protocol: InsProtocol = "nmea",
    ins_rate: InsRate = 100.0,
    surroundings: Annotated[
        bool,
        typer.Option(
            "--surroundings/--no-surroundings",
            help="Add the quay around the scenario's scene (a long quay wall, a warehouse, the water near "
            "the vessel) so that the survey sees more than the calibration targets.",
        ),
    ] = True,
    rotate_s: Annotated[
        float | None,
        typer.Option(
            "--rotate-s",
            min=10.0,
            help="Segment rotation period in session seconds (default: the daemon's, 600).",
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        set_option(
            "Override a scenario value by dotted key, e.g. --set site.pass_length_m=120 "
            "--set motion.pass_gap_s=20 (repeatable; values are YAML)."
        ),
    ] = None,
) -> None:
    """Write a recorded session offline, faster than real time, from a simulator scenario.

    The vessel sails lines back and forth along the quay (the scenario's line length, speed,
    standoff and gap) for --minutes while the profiler records its full circle; the session
    directory created in --out holds what the daemon would have written with the emulators as
    its devices: MCAP segments (/ins/raw, /ins/nav, /lidar/raw, /pps, /can/marks, /events with a
    pass_start/pass_end per line, /clock, /latency), vessel.yaml, site.yaml, session.json (with
    the simulation's settings) and truth.json. A session of the same name is refused unless --force."""
    import time

    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from calib.core.errors import MlsError
    from office.simsession.record import SessionSpec, plan_session, record_session

    console = Console(emoji=False)  # ":100:" of file:line:column is no emoji
    spec = SessionSpec(
        scenario=scenario,
        out=out,
        minutes=minutes,
        rate_scale=rate_scale,
        seed=seed,
        force=force,
        overrides=tuple(set_ or ()),
        ins_protocol=ins_protocol,
        ins_rate_hz=ins_rate,
        surroundings=surroundings,
        rotate_s=rotate_s,
    )
    try:
        with simulation_bar(console, f"sailing the survey ({scenario}, {minutes:g} min)") as (_, _, progress):
            plan = plan_session(spec, progress)
        columns = (
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
            TextColumn("{task.fields[rate]}"),
            TimeRemainingColumn(),
        )
        t0 = time.perf_counter()
        with Progress(*columns, console=console, transient=True) as bar:
            task = bar.add_task("writing the session", total=plan.duration_s, rate="")

            def written(done_s: float, total_s: float, returns: int) -> None:
                rate = returns / max(time.perf_counter() - t0, 1e-9)
                bar.update(task, completed=done_s, total=total_s, rate=f"{rate / 1e6:.2f} M returns/s")

            result = record_session(plan, written)
    except (MlsError, OSError) as e:
        console.print(f"[red]error:[/red] {escape(str(e))}", highlight=False, soft_wrap=True)  # one line
        raise typer.Exit(2) from None
    except KeyboardInterrupt:
        console.print("interrupted: the session written so far was closed", highlight=False)
        raise typer.Exit(130) from None
    r = result
    mb = r.bytes_written / 1e6
    console.print(
        f"wrote {r.path}: {r.duration_s / 60:g} min, {r.returns:,} returns ({r.points:,} points: "
        f"{r.profile_rate_hz:.1f} profiles/s × {r.points // max(r.profiles, 1)}), "
        f"{len(r.passes)} pass{'es' if len(r.passes) != 1 else ''}, "
        f"{r.segments} segment{'s' if r.segments != 1 else ''}, {mb:.1f} MB in {r.wall_s:.1f} s "
        f"({r.returns / r.wall_s / 1e6:.2f} M returns/s, {mb / r.wall_s:.1f} MB/s)",
        highlight=False,
        soft_wrap=True,
    )

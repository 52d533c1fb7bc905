"""Site what-if (``mls design --site``): the predicted σ of a planned site config after each pass
in its sailing order, and the pass that would help most next (by the realistic σ: the GLS
estimator's, the calibration's default); with piles in the site config, the lines for yaw
(:mod:`calib.design.yawlines`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.core import frames
from calib.design.layouts import Layout
from calib.design.prediction import (
    DesignError,
    Sigmas,
    predict,
    prepare,
    scan_angle_roll_correlation,
    select_passes,
)
from calib.design.scenes import design_scenario
from calib.design.study import SIGMA_COLUMNS, headings_deg, sigma_row
from calib.design.summary import write_csv
from calib.design.yawlines import YAW_LINE_COLUMNS, yaw_lines_or_why
from calib.io.site import Site
from calib.sim.noise import PosNoise, ScannerNoise
from calib.sim.scenario import Pile, Scenario, Surface
from calib.sim.scenariofile import load_scenario


def _target_surfaces(site: Site, sc: Scenario) -> tuple[Surface, ...]:
    """The site's targets as surfaces of ``sc`` (its frame and wall): their sizes, inclinations
    and facings relative to the water."""
    surfaces = []
    for t in site.targets:
        along, out, up = sc.lgf_to_site(t.rectangle(sc.reference).center_m)
        facing = float(frames.wrap_pi(t.facing_azimuth_rad - sc.water_azimuth_rad))
        surfaces.append(
            Surface(
                t.name,
                "target",
                along,
                out,
                up,
                t.width_m,
                t.height_along_slope_m,
                t.inclination_rad,
                facing,
                t.reflectivity,
            )
        )
    return tuple(surfaces)


def _site_piles(site: Site, sc: Scenario) -> tuple[Pile, ...]:
    """The site's piles as piles of ``sc`` (its frame and wall)."""
    out = []
    for p in site.piles:
        c = p.cylinder(sc.reference)
        along, off, up = sc.lgf_to_site(c.center_m)
        half_m = 0.5 * c.height_m
        out.append(
            Pile(
                name=p.name,
                along_m=along,
                out_m=off,
                bottom_up_m=up - half_m,
                top_up_m=up + half_m,
                diameter_m=p.diameter_m,
            )
        )
    return tuple(out)


def _site_pos_noise(site: Site) -> PosNoise:
    """Gauss–Markov POS errors with the site's sigmas and correlation times."""
    tau = Sigmas.of_site(site).correlation_time_s
    return PosNoise(
        "gauss_markov",
        site.sigma_position_m,
        site.sigma_attitude_rad,
        np.asarray(tau[0:3]),
        np.asarray(tau[3:6]),
    )


def site_as_scenario(
    site: Site, template: Scenario | str = "montreal", scanner_height_m: float | None = None
) -> Scenario:
    """A site config as a design scenario: its targets, wall azimuth, standoff, passes, mount
    and sigmas; the profiler, the motion and the noise models' kinds from ``template``. The
    vessel's scanner sails at ``scanner_height_m`` (ellipsoidal; default: the reference
    height)."""
    tpl = template if isinstance(template, Scenario) else load_scenario(template)
    if site.reference is None:
        raise DesignError(
            "the site config has no 'reference': the what-if needs the LGF origin "
            "(and, by default, the scanner's height) from it"
        )
    if not site.targets:
        raise DesignError("the site config has no targets")
    ref = site.reference
    h = ref.height_m if scanner_height_m is None else float(scanner_height_m)
    placed = replace(
        tpl,
        reference=frames.LocalFrame(ref.lat_deg, ref.lon_deg, h),
        wall_azimuth_rad=float(site.wall_azimuth_rad),
    )
    return replace(
        placed,
        name="site",
        description="site config what-if",
        standoff_m=float(site.standoff_m),
        passes=site.passes,
        surfaces=_target_surfaces(site, placed),
        piles=_site_piles(site, placed),
        mount=site.mount,
        truth=replace(
            tpl.truth,
            boresight_rad=np.asarray(site.mount.boresight_rad, float),
            lever_arm_error_m=np.zeros(3),
            range_offset_m=0.0,
            scan_angle_offset_rad=0.0,
            time_offset_s=0.0,
        ),
        scanner_noise=ScannerNoise(
            sigma_range_m=site.sigma_range_m,
            sigma_range_per_m=site.sigma_range_per_m,
            beam_divergence_rad=site.beam_divergence_rad,
            sigma_scan_angle_rad=site.sigma_scan_angle_rad,
        ),
        pos_noise=_site_pos_noise(site),
    )


@dataclass(frozen=True)
class WhatIf:
    """Predicted σ of a planned site: after each pass in the sailing order, and the pass that
    would help most next."""

    scenario: Scenario
    rows: list  # one per step: sigma_row(...) + "next_best_pass"
    roll_scan_correlation: float
    yaw_lines: list = field(default_factory=list)  # with piles in the site (calib.design.yawlines)
    yaw_lines_note: str = ""


def what_if(
    site: Site, template: Scenario | str = "montreal", scanner_height_m: float | None = None, seed: int = 0
) -> WhatIf:
    sc = site_as_scenario(site, template, scanner_height_m)
    sigmas = Sigmas.of_site(site)
    sim, obs, planes = prepare(design_scenario(sc, sc.surfaces), sigmas, seed)
    order = [p.id for p in sorted(sim.plan.passes, key=lambda q: q.order)]
    lay = Layout("site", "site", sc.surfaces, sc.standoff_m, ())
    headings, tau = headings_deg(sc), sigmas.correlation_time_s

    def row(subset):
        o, p = select_passes(obs, planes, subset)
        return sigma_row(sc.name, lay, predict(o, sim.mount_true, p, tau), subset, headings, tau)

    rows = []
    for k in range(1, len(order) + 1):
        r = row(order[:k])
        rest = order[k:]
        nxt = {q: row(order[:k] + [q])["realistic_total_deg"] for q in rest}
        r["next_best_pass"] = min(nxt, key=lambda q: nxt[q]) if nxt else ""
        rows.append(r)
    rho = scan_angle_roll_correlation(obs, sim.mount_true, planes)
    yaw, why = yaw_lines_or_why(sc, sigmas, seed=seed) if sc.piles else ([], "the site config lists no piles")
    return WhatIf(scenario=sc, rows=rows, roll_scan_correlation=rho, yaw_lines=yaw, yaw_lines_note=why)


def write_what_if(w: WhatIf, out_dir: str | Path) -> list[Path]:
    from calib.io.outputs import make_output_dir

    out = make_output_dir(out_dir)
    files = [write_csv(out / "whatif.csv", w.rows, list(SIGMA_COLUMNS) + ["next_best_pass"])]
    if w.yaw_lines:
        files.append(write_csv(out / "yaw_lines.csv", w.yaw_lines, YAW_LINE_COLUMNS))
    return files

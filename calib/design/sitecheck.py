"""Monte Carlo check of a recommendation (``mls design --seeds N``): the recommended site and
the scenario's own site, each simulated with the scenario's noise and adjusted seed by seed, and
their RMS boresight errors side by side (the ``empirical`` part of :func:`calib.design.summary.
write_study`)."""

from __future__ import annotations

import numpy as np

from calib.design.montecarlo import empirical_errors
from calib.design.scenes import site_scenario

#: the adjustments of the scenario's own site (the recommended one gets its own estimator)
_OWN = {"gls": "GLS (default)", "thesis": "thesis adjustment", "pass_offsets": "pass offsets"}


def compare_sites(base, rec, seeds: int, jobs: int, progress) -> dict:
    """Both sites simulated with the scenario's noise, adjusted; RMS errors side by side.

    ``base`` is the scenario, ``rec`` the study's recommendation; returns ``rms_deg`` (per
    site and adjustment, roll, pitch, yaw in degrees), ``seeds`` and ``text`` (a Markdown
    table for summary.md)."""
    own = site_scenario(base, [s for s in base.surfaces if s.kind == "target"])
    new = site_scenario(base, rec.layout.targets)
    n = int(seeds)
    est = rec.estimator_name
    errs_own = empirical_errors(own, range(n), tuple(_OWN), jobs, progress)
    errs_new = empirical_errors(new, range(n), (est,), jobs, progress)
    runs = {f"scenario's site, {label}": errs_own[e] for e, label in _OWN.items()}
    runs[f"recommended site, {_OWN[est]}"] = errs_new[est]
    rms = {name: np.degrees(np.sqrt(np.mean(e**2, axis=0))) for name, e in runs.items()}
    lines = [
        f"{n} simulations of each site with the scenario's noise ({base.pos_noise.model} POS "
        f"errors), adjusted; RMS error of the estimates:",
        "",
        "| site and adjustment | roll | pitch | yaw | total |",
        "|---|---|---|---|---|",
    ]
    for name, r in rms.items():
        lines.append(
            f"| {name} | {r[0]:.4f}° | {r[1]:.4f}° | {r[2]:.4f}° | {float(np.sqrt(np.sum(r**2))):.4f}° |"
        )
    return {"rms_deg": rms, "seeds": n, "text": "\n".join(lines)}

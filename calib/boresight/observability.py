"""Whether the boresight is determined, and what would determine it (thesis §4.4.1.1).

On a vertical target the reciprocal parallel pair (0°/180°) observes roll, a side-looking
reciprocal pair (45°/225° or 315°/135°) pitch and a crossing pair (45°/135° or 315°/225°) yaw.
A weak angle is an error that names it, its σ, and the passes (or the target geometry) that
would observe it — instead of a number.
"""

from __future__ import annotations

import numpy as np

from calib.boresight.observations import AdjustmentError, Observations

ANGLE_NAMES = ("roll", "pitch", "yaw")


class ObservabilityError(AdjustmentError):
    """The boresight (or a combination of angles) is not determined by the passes and targets."""


class SingularError(ObservabilityError):
    """The normal equations are singular; ``unknowns`` names those of their null direction,
    largest share first (e.g. ``cyl_008.d``: a feature whose own parameters the data leave free)."""

    def __init__(self, message: str, unknowns: tuple[str, ...] = ()):
        super().__init__(message)
        self.unknowns = tuple(unknowns)


#: Which reciprocal/crossing pass pairs (headings relative to the wall, degrees) observe which
#: boresight angle on a vertical target (thesis §4.4.1.1).
OBSERVING_PAIRS = {
    0: ("the reciprocal parallel pair 0°/180°", ((0, 180),)),
    1: ("a side-looking reciprocal pair 45°/225° or 315°/135°", ((45, 225), (315, 135))),
    2: ("a crossing pair 45°/135° or 315°/225°", ((45, 135), (315, 225))),
}


def sailed_headings(obs: Observations) -> set[int]:
    """Relative headings of the passes, snapped to the 45° grid when within 15°."""
    out = set()
    for pid in obs.pass_ids:
        h = obs.pass_headings_rad.get(pid)
        if h is None:
            continue
        deg = np.degrees(h) % 360.0
        snap = int(round(deg / 45.0)) * 45 % 360
        if abs((deg - snap + 180.0) % 360.0 - 180.0) <= 15.0:
            out.add(snap)
    return out


def check_observability(
    cov_bs: np.ndarray, obs: Observations, max_sigma_rad: float, estimate: tuple[str, ...] = ()
) -> None:
    """Raise :class:`ObservabilityError` when a boresight angle (or a combination) is weak,
    naming the angle(s) and what would observe them."""
    sig = np.sqrt(np.clip(np.diag(cov_bs), 0, None))
    vals, vecs = np.linalg.eigh(cov_bs)
    weak_dirs = [vecs[:, i] for i in range(3) if np.sqrt(max(vals[i], 0)) > max_sigma_rad]
    if not weak_dirs:
        return
    weak = sorted(
        {int(np.argmax(np.abs(v))) for v in weak_dirs} | {i for i in range(3) if sig[i] > max_sigma_rad}
    )
    sailed = sailed_headings(obs)
    passes = ", ".join(
        f"{pid}"
        + (
            f" ({round(float(np.degrees(obs.pass_headings_rad[pid]))) % 360}°)"
            if pid in obs.pass_headings_rad
            else ""
        )
        for pid in obs.pass_ids
    )
    advice = []
    for i in weak:
        label, pairs = OBSERVING_PAIRS[i]
        if sailed and not any(a in sailed and b in sailed for a, b in pairs):
            advice.append(f"for {ANGLE_NAMES[i]} sail {label}")
    if not advice:
        cause = (
            (
                "the per-pass trajectory offsets look like a boresight rotation with these "
                "targets: spread targets in range, height and along the wall, or do not "
                "estimate pass_offsets"
            )
            if "pass_offsets" in estimate
            else (
                "the targets do not separate the angles: use at least two targets with "
                "different inclinations (vertical and 45°), spread along the wall"
            )
        )
        extra = [e for e in estimate if e != "pass_offsets"]
        if extra:
            cause += f"; the extra unknowns {', '.join(extra)} may also absorb the boresight"
        advice.append(cause)
    angles = " and ".join(ANGLE_NAMES[i] for i in weak)
    detail = ", ".join(f"{ANGLE_NAMES[i]} σ = {np.degrees(sig[i]):.3g}°" for i in weak)
    raise ObservabilityError(
        f"boresight {angles} {'is' if len(weak) == 1 else 'are'} not observable with passes "
        f"{passes} and planes {', '.join(obs.plane_names)} ({detail}, limit "
        f"{np.degrees(max_sigma_rad):.3g}°): {'; '.join(advice)} (thesis §4.4.1.1)."
    )

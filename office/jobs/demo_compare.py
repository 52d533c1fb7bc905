"""The end of ``mls demo`` (:mod:`office.jobs.demo`): the recovered boresight against the truth the
simulated devices were fed, canonical and in the thesis convention (:func:`comparison_rows`), and
its table (:func:`comparison_table`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

ANGLES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class AngleComparison:
    angle: str
    convention: str  # "canonical" | "thesis"
    truth_deg: float
    recovered_deg: float
    sigma_formal_deg: float
    sigma_realistic_deg: float

    @property
    def error_deg(self) -> float:
        return self.recovered_deg - self.truth_deg

    @property
    def error_sigmas(self) -> float:
        """The error in units of the realistic σ."""
        return self.error_deg / self.sigma_realistic_deg if self.sigma_realistic_deg > 0 else math.inf


def comparison_rows(result: dict, truth: dict) -> list[AngleComparison]:
    """Recovered (``result.json``) against the truth (``scenario_truth.json``), canonical and
    in the thesis convention (roll, −pitch, yaw; docs/architecture.md §3)."""
    b, sf, sr = result["boresight_deg"], result["sigma_deg"], result["sigma_realistic_deg"]
    t = truth["boresight_deg"]
    rows = [
        AngleComparison(a, "canonical", float(t[a]), float(b[a]), float(sf[a]), float(sr[a])) for a in ANGLES
    ]
    sign = {"roll": 1.0, "pitch": -1.0, "yaw": 1.0}
    rows += [
        AngleComparison(
            r.angle,
            "thesis",
            sign[r.angle] * r.truth_deg,
            sign[r.angle] * r.recovered_deg,
            r.sigma_formal_deg,
            r.sigma_realistic_deg,
        )
        for r in rows
    ]
    return rows


def comparison_table(rows: list[AngleComparison]):
    from rich import box
    from rich.table import Table

    t = Table(
        title="boresight: recovered vs truth (degrees)",
        box=box.SIMPLE_HEAD,
        title_justify="left",
        pad_edge=False,
        show_edge=False,
    )
    for col in ("", "truth", "recovered", "error", "σ formal", "σ realistic", "error/σ"):
        t.add_column(col, justify="right" if col else "left", no_wrap=True)
    for i, r in enumerate(rows):
        if i and r.convention != rows[i - 1].convention:
            t.add_section()
        name = r.angle if r.convention == "canonical" else f"thesis {r.angle}"
        bad = abs(r.error_sigmas) > 3
        t.add_row(
            name,
            f"{r.truth_deg:+.4f}",
            f"{r.recovered_deg:+.4f}",
            f"{r.error_deg:+.4f}",
            f"{r.sigma_formal_deg:.4f}",
            f"{r.sigma_realistic_deg:.4f}",
            f"[{'bold red' if bad else 'green'}]{r.error_sigmas:+.2f}[/]",
        )
    t.caption = (
        "canonical: docs/architecture.md §3 (R_bs = Rz(yaw)·Ry(pitch)·Rx(roll), pitch + bow up); thesis: "
        "the iXblue/NWU convention of Shahraji 2022 (pitch negated); error/σ in realistic σ"
    )
    t.caption_justify = "left"
    return t

"""The mount watch's sequential test and running estimate, block by block.

**The test** (:class:`MountTest`): for each angle (roll, pitch, yaw) and each sign, a CUSUM of
the log-likelihood ratio of "the boresight moved by ±μ on this angle" against "it did not"::

    Λ_b = (±μ / σ_b²) · (δ_b ∓ μ/2),     S_b = max(0, S_{b−1} + Λ_b),     alarm when S_b ≥ h

where ``δ_b`` is the block's correction of that angle and ``σ_b`` its σ (the marginal of the
block's covariance: the other angles are nuisances). A block that observes an angle poorly has a
large ``σ_b`` and moves the statistic hardly at all: a line without patches is no evidence. The
design shift ``μ`` (:attr:`WatchDesign.shift_rad`) is the change the test is tuned to detect
fastest; larger changes are detected faster still, smaller ones later.

**Families.** Consecutive blocks share a line (:class:`calib.watch.runner.BlockCutter`: each
line closes a block with the one before it), so they are not independent; they are dealt into
:data:`FAMILIES` interleaved families whose blocks share no line, and each family has its own
six statistics. The alarm is raised by whichever family crosses first.

**The false-alarm rate.** For a CUSUM of log-likelihood ratios of independent blocks, the mean
number of blocks to a false alarm is at least ``e^h`` (Lorden 1971; the bound holds for any
σ_b sequence, since each Λ_b is a likelihood ratio with expectation 1 of ``e^Λ`` under no
change). Each family runs six one-sided statistics, so with at most ``B`` blocks per hour in a
family the false alarms per hour are at most ``6·FAMILIES·B·e^{−h}`` (a union bound: the
families need not be independent of each other); :meth:`WatchDesign.threshold` solves that for
the requested rate (default :data:`FALSE_ALARMS_PER_HOUR`: one in 100 survey hours). The bound
is conservative, and it assumes the σ_b are right: a model that understates them raises the
rate, which is why blocks scale their covariance by the variance factor and the benchmark
measures the rate on data the model did not generate (``benchmarks/watch.py``).

**The running estimate** (:class:`MountTest.estimate_rad`): a Kalman filter of the correction as
a random walk (:attr:`WatchDesign.walk_rad_per_sqrt_h`) updated with each block — it follows a
slow creep and settles on a step; every line is in two blocks, so each block enters it with
twice its covariance. **The alarm's size** is the information-weighted mean of the blocks of
the alarmed statistic's run (in its family) — from the block where it last left zero, the
CUSUM's estimate of the change time — after that first block, which holds the change only in
part; with its σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from calib.core.frames import gps_ns_to_utc
from calib.watch.block import BlockEstimate

ANGLES = ("roll", "pitch", "yaw")
FALSE_ALARMS_PER_HOUR = 0.01  # one in 100 survey hours
MAX_BLOCKS_PER_HOUR = 60.0  # in a family: a block is two lines of at least half a minute each
FAMILIES = 2  # interleaved block sequences (module docstring)
UNSEEN_RAD = 100.0  # the σ given to an angle a block does not observe


@dataclass(frozen=True)
class WatchDesign:
    shift_rad: float = float(np.radians(0.1))  # the change the CUSUM is tuned to
    false_alarms_per_hour: float = FALSE_ALARMS_PER_HOUR
    max_blocks_per_hour: float = MAX_BLOCKS_PER_HOUR
    walk_rad_per_sqrt_h: float = float(np.radians(0.05))  # the running estimate's random walk
    #: an angle a block resolves no better than this is not observed by it (no evidence)
    max_sigma_rad: float = float(np.radians(0.1))

    def __post_init__(self):
        if not self.shift_rad > 0 or not self.false_alarms_per_hour > 0 or not self.max_blocks_per_hour > 0:
            raise ValueError("watch test: shift, false-alarm rate and blocks per hour must be > 0")

    @property
    def threshold(self) -> float:
        """h such that 6 one-sided CUSUMs in each family at ``max_blocks_per_hour`` raise at
        most ``false_alarms_per_hour`` (Lorden's bound, module docstring)."""
        return math.log(6.0 * FAMILIES * self.max_blocks_per_hour / self.false_alarms_per_hour)

    def as_dict(self) -> dict:
        return {
            "shift_deg": math.degrees(self.shift_rad),
            "false_alarms_per_hour": self.false_alarms_per_hour,
            "max_blocks_per_hour": self.max_blocks_per_hour,
            "families": FAMILIES,
            "threshold": self.threshold,
            "walk_deg_per_sqrt_h": math.degrees(self.walk_rad_per_sqrt_h),
        }


@dataclass(frozen=True)
class MountAlarm:
    """The test crossed its threshold on these angles."""

    t_gps_s: float  # the end of the block that crossed
    since_gps_s: float  # the estimated change time: the start of the first block of the run
    #: the size: information-weighted mean of the run's blocks after its first (the first,
    #: during which the change happened, holds only part of it), or of the first alone
    angles: tuple[str, ...]
    size_rad: np.ndarray  # (3,) mean correction since then (all angles)
    sigma_rad: np.ndarray  # (3,)
    statistic: float
    first_block: int = 0  # index of the run's first block (the one the change happened in)
    blocks_after: int = 0  # blocks of the size after that one (0: the first alone)

    def message(self) -> str:
        parts = [
            f"{a} {math.degrees(self.size_rad[ANGLES.index(a)]):+.3f}° ± "
            f"{math.degrees(self.sigma_rad[ANGLES.index(a)]):.3f}°"
            for a in self.angles
        ]
        since = gps_ns_to_utc(round(self.since_gps_s * 1e9)).strftime("%Y-%m-%d %H:%M:%S UTC")
        note = "" if self.blocks_after > 0 else " (from the block the change happened in: a part of it)"
        return f"{', '.join(parts)} since {since}{note}"

    def as_dict(self) -> dict:
        return {
            "t_gps_s": self.t_gps_s,
            "since_gps_s": self.since_gps_s,
            "angles": list(self.angles),
            "size_deg": [math.degrees(x) for x in self.size_rad],
            "sigma_deg": [math.degrees(x) for x in self.sigma_rad],
            "statistic": self.statistic,
            "blocks_after": self.blocks_after,
            "message": self.message(),
        }


@dataclass
class MountTest:
    """The sequential test over blocks (module docstring). ``update`` each block in time order."""

    design: WatchDesign = field(default_factory=WatchDesign)
    S: np.ndarray = field(default_factory=lambda: np.zeros((FAMILIES, 3, 2)))  # [family, angle, (+, −)]
    run_start: np.ndarray = field(default_factory=lambda: np.full((FAMILIES, 3, 2), -1, int))  # block
    estimate_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov_rad2: np.ndarray = field(default_factory=lambda: np.eye(3) * np.radians(1.0) ** 2)
    blocks: list[BlockEstimate] = field(default_factory=list)
    families: list[int] = field(default_factory=list)  # each block's
    alarm: MountAlarm | None = None
    _t_last: float | None = None

    def update(self, block: BlockEstimate, family: int = 0) -> MountAlarm | None:
        """Take one block of a family; returns the alarm when this block raised it (once)."""
        if not 0 <= family < FAMILIES:
            raise ValueError(f"watch test: family {family} outside 0…{FAMILIES - 1}")
        self.blocks.append(block)
        self.families.append(family)
        b = len(self.blocks) - 1
        if not block.ok:
            return None
        delta, cov, seen = self.usable(block)
        if not seen.any():
            return None
        self._filter(block, delta, cov)
        mu = self.design.shift_rad
        var = np.diag(cov)
        S, start = self.S[family], self.run_start[family]
        for s, sign in enumerate((1.0, -1.0)):
            llr = np.where(seen, (sign * mu / var) * (delta - sign * mu / 2.0), 0.0)
            new = S[:, s] + llr
            start[(S[:, s] <= 0.0) & (new > 0.0), s] = b
            S[:, s] = np.maximum(0.0, new)
            start[S[:, s] <= 0.0, s] = -1
        if self.alarm is None:
            hit = S.max(axis=1) >= self.design.threshold
            if hit.any():
                self.alarm = self._raise(b, family, hit)
                return self.alarm
        else:  # raised once; its size keeps being refined by the blocks after the change
            self.alarm = self._sized(self.alarm, self.alarm.first_block, b)
        return None

    @property
    def statistic(self) -> np.ndarray:
        """(3,) the largest of each angle's CUSUMs, over the threshold (alarm at 1)."""
        return self.S.max(axis=(0, 2)) / self.design.threshold

    @property
    def sigma_rad(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov_rad2))

    def usable(self, block: BlockEstimate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The block's correction and covariance as the test uses them, and which angles it
        observes (σ ≤ :attr:`WatchDesign.max_sigma_rad`): the others get a variance of
        :data:`UNSEEN_RAD`² and no correlation (no evidence)."""
        if block.delta_rad is None or block.cov_rad2 is None:
            return np.zeros(3), np.eye(3) * UNSEEN_RAD**2, np.zeros(3, bool)
        seen = block.sigma_rad <= self.design.max_sigma_rad
        cov = np.diag(np.where(seen, 0.0, UNSEEN_RAD**2))
        cov[np.ix_(seen, seen)] = block.cov_rad2[np.ix_(seen, seen)]
        return np.where(seen, block.delta_rad, 0.0), cov, seen

    def _filter(self, block: BlockEstimate, delta: np.ndarray, R: np.ndarray) -> None:
        t = 0.5 * (block.t_start_gps_s + block.t_end_gps_s)
        if self._t_last is not None:
            q = self.design.walk_rad_per_sqrt_h**2 * max(t - self._t_last, 0.0) / 3600.0
            self.cov_rad2 = self.cov_rad2 + q * np.eye(3)
        self._t_last = t
        P = self.cov_rad2
        K = P @ np.linalg.inv(P + FAMILIES * R)  # every line is in FAMILIES blocks
        self.estimate_rad = self.estimate_rad + K @ (delta - self.estimate_rad)
        self.cov_rad2 = (np.eye(3) - K) @ P
        self.cov_rad2 = 0.5 * (self.cov_rad2 + self.cov_rad2.T)

    def _raise(self, b: int, family: int, hit: np.ndarray) -> MountAlarm:
        angles = tuple(ANGLES[i] for i in np.flatnonzero(hit))
        S, start = self.S[family], self.run_start[family]
        side = np.argmax(S, axis=1)
        starts = [start[i, side[i]] for i in np.flatnonzero(hit)]
        first = min(s for s in starts if s >= 0) if any(s >= 0 for s in starts) else b
        alarm = MountAlarm(
            t_gps_s=self.blocks[b].t_end_gps_s,
            since_gps_s=self.blocks[first].t_start_gps_s,
            angles=angles,
            size_rad=np.zeros(3),
            sigma_rad=np.zeros(3),
            statistic=float(S.max()),
            first_block=int(first),
        )
        return self._sized(alarm, first, b)

    def _sized(self, alarm: MountAlarm, first: int, b: int) -> MountAlarm:
        """``alarm`` with its size from the blocks ``first``…``b`` of the first one's family
        (which share no line): those after the first (during which the change happened, so
        that it holds only part of it), or the first alone."""
        family = self.families[first]
        run = [
            blk
            for blk, f in zip(self.blocks[first : b + 1], self.families[first : b + 1], strict=False)
            if blk.ok and f == family
        ]
        used = run[1:] if len(run) > 1 else run
        parts = [self.usable(blk) for blk in used]
        info = sum(np.linalg.inv(c) for _, c, _ in parts)
        cov = np.linalg.inv(info)
        size = cov @ sum(np.linalg.inv(c) @ d for d, c, _ in parts)
        return replace(alarm, size_rad=size, sigma_rad=np.sqrt(np.diag(cov)), blocks_after=len(run) - 1)

    def state(self) -> dict:
        """What the watch publishes (degrees at the edge)."""
        last = next((b for b in reversed(self.blocks) if b.ok), None)
        return {
            "estimate_deg": [math.degrees(x) for x in self.estimate_rad],
            "sigma_deg": [math.degrees(x) for x in self.sigma_rad],
            "statistic": [float(x) for x in self.statistic],
            "threshold": self.design.threshold,
            "blocks": len(self.blocks),
            "blocks_ok": sum(b.ok for b in self.blocks),
            "last_block": None if last is None else last.as_dict() | {"patches": len(last.patches)},
            "alarm": None if self.alarm is None else self.alarm.as_dict(),
        }

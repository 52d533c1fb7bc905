"""Trajectory: GPS-timed positions (LGF, NED) and attitude (canonical), optional per-epoch sigmas.

Interpolation at arbitrary point times: positions linear in the LGF, attitude by spherical
interpolation of the rotation (``R(t) = R_k · Exp(w · φ_k)`` with ``φ_k = Log(R_kᵀ R_{k+1})``), so
a heading step across 359.9° → 0.1° stays between its two samples; sigmas linear. Times that fall
outside the trajectory, or inside a gap longer than ``max_gap_s``, are refused with an error that
says which times they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from calib.core import frames
from calib.core.errors import CalibError


class TrajectoryError(CalibError, ValueError):
    """A trajectory is malformed or does not cover the requested times."""


@dataclass(frozen=True)
class Poses:
    """Poses interpolated at n point times."""

    p_lgf_m: np.ndarray  # (n, 3) NED
    rpy_rad: np.ndarray  # (n, 3) roll, pitch, heading (heading in [0, 2π))
    r_b_n: np.ndarray  # (n, 3, 3) body → LGF
    sigma_p_m: np.ndarray | None = None  # (n, 3) north, east, down
    sigma_rpy_rad: np.ndarray | None = None  # (n, 3) roll, pitch, heading


@dataclass(frozen=True)
class Trajectory:
    """A trajectory in the LGF of ``frame``.

    ``t_gps_s`` strictly increasing float64 seconds since the GPS epoch; ``p_lgf_m`` (n, 3) NED;
    ``rpy_rad`` (n, 3) roll, pitch, heading in canonical convention; optional (n, 3) sigmas.
    """

    t_gps_s: np.ndarray
    p_lgf_m: np.ndarray
    rpy_rad: np.ndarray
    frame: frames.LocalFrame
    sigma_p_m: np.ndarray | None = None
    sigma_rpy_rad: np.ndarray | None = None
    max_gap_s: float = 1.0
    name: str = field(default="trajectory", compare=False)

    def __post_init__(self):
        t = np.asarray(self.t_gps_s, dtype=float)
        object.__setattr__(self, "t_gps_s", t)
        for attr in ("p_lgf_m", "rpy_rad", "sigma_p_m", "sigma_rpy_rad"):
            v = getattr(self, attr)
            if v is None:
                continue
            v = np.asarray(v, dtype=float)
            if v.shape != (t.size, 3):
                raise TrajectoryError(f"{self.name}: {attr} has shape {v.shape}, expected ({t.size}, 3)")
            object.__setattr__(self, attr, v)
        if t.ndim != 1 or t.size < 2:
            raise TrajectoryError(f"{self.name}: needs at least 2 epochs, got {t.size}")
        bad = ~np.isfinite(t)
        if bad.any():
            raise TrajectoryError(f"{self.name}: non-finite time at epoch {int(np.argmax(bad))}")
        steps = np.diff(t)
        if np.any(steps <= 0):
            i = int(np.argmax(steps <= 0))
            raise TrajectoryError(
                f"{self.name}: times must increase strictly; epoch {i + 1} "
                f"(t={t[i + 1]:.6f}) follows t={t[i]:.6f}"
            )
        for attr in ("p_lgf_m", "rpy_rad"):
            v = getattr(self, attr)
            if not np.all(np.isfinite(v)):
                i = int(np.argmax(~np.all(np.isfinite(v), axis=1)))
                raise TrajectoryError(f"{self.name}: non-finite {attr} at epoch {i}")

    # -- construction ----------------------------------------------------------------------

    @classmethod
    def from_geodetic(
        cls,
        t_gps_s,
        lat_deg,
        lon_deg,
        height_m,
        rpy_rad,
        frame: frames.LocalFrame | None = None,
        **kwargs,
    ) -> Trajectory:
        """Build from geodetic positions; the LGF reference defaults to the mean position."""
        if frame is None:
            frame = frames.LocalFrame.at_mean(lat_deg, lon_deg, height_m)
        p = frame.to_lgf(lat_deg, lon_deg, height_m)
        return cls(np.asarray(t_gps_s, float), p, np.asarray(rpy_rad, float), frame, **kwargs)

    def geodetic(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lat_deg, lon_deg, height_m) of every epoch."""
        return self.frame.to_geodetic(self.p_lgf_m)

    def with_frame(self, frame: frames.LocalFrame) -> Trajectory:
        """The same trajectory expressed in another LGF (attitude is kept: the frames are
        assumed close enough that the tangent-plane rotation between them is negligible)."""
        if frame == self.frame:
            return self
        lat, lon, h = self.geodetic()
        return Trajectory(
            self.t_gps_s,
            frame.to_lgf(lat, lon, h),
            self.rpy_rad,
            frame,
            self.sigma_p_m,
            self.sigma_rpy_rad,
            self.max_gap_s,
            self.name,
        )

    def select(self, mask_or_slice) -> Trajectory:
        sel = lambda a: None if a is None else a[mask_or_slice]  # noqa: E731
        return Trajectory(
            self.t_gps_s[mask_or_slice],
            self.p_lgf_m[mask_or_slice],
            self.rpy_rad[mask_or_slice],
            self.frame,
            sel(self.sigma_p_m),
            sel(self.sigma_rpy_rad),
            self.max_gap_s,
            self.name,
        )

    @property
    def has_sigmas(self) -> bool:
        return self.sigma_p_m is not None and self.sigma_rpy_rad is not None

    # -- per-interval quantities (cached) ---------------------------------------------------

    @cached_property
    def r_b_n(self) -> np.ndarray:
        """(n, 3, 3) attitude matrices of the epochs."""
        return frames.attitude_matrix(*self.rpy_rad.T)

    @cached_property
    def interval_rotvec(self) -> np.ndarray:
        """(n−1, 3) body-frame rotation vectors ``φ_k = Log(R_kᵀ R_{k+1})``."""
        R = self.r_b_n
        rel = np.einsum("kji,kjl->kil", R[:-1], R[1:])
        return frames.vector_from_rotation(rel)

    # -- interpolation ----------------------------------------------------------------------

    def locate(self, t_gps_s) -> tuple[np.ndarray, np.ndarray]:
        """Interval index k and fraction w ∈ [0, 1] for each time; refuses uncovered times."""
        t = np.asarray(t_gps_s, dtype=float)
        self.check_coverage(t)
        tt = self.t_gps_s
        k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, tt.size - 2)
        w = (t - tt[k]) / (tt[k + 1] - tt[k])
        return k, w

    def uncovered(self, t_gps_s) -> np.ndarray:
        """Boolean mask of times that cannot be interpolated (outside, in a gap, or NaN)."""
        t = np.asarray(t_gps_s, dtype=float)
        tt = self.t_gps_s
        bad = ~np.isfinite(t) | (t < tt[0]) | (t > tt[-1])
        gaps = np.diff(tt) > self.max_gap_s
        if gaps.any():
            k = np.clip(np.searchsorted(tt, np.where(bad, tt[0], t), side="right") - 1, 0, tt.size - 2)
            bad |= gaps[k] & (t != tt[k]) & (t != tt[k + 1])  # a gap's end samples are fine
        return bad

    def where_uncovered(self, t_gps_s) -> str:
        """Where the times :meth:`uncovered` refuses fall, for a message: before the first epoch,
        after the last, in which gaps (epoch times, the first three), NaN; "" when none."""
        t = np.asarray(t_gps_s, dtype=float)
        bad, tt = self.uncovered(t), self.t_gps_s
        parts = []
        for n, what in (
            (int(np.sum(bad & (t < tt[0]))), f"before its first epoch {tt[0]:.3f} s"),
            (int(np.sum(bad & (t > tt[-1]))), f"after its last epoch {tt[-1]:.3f} s"),
        ):
            if n:
                parts.append(f"{n} {what}")
        inside = bad & (t >= tt[0]) & (t <= tt[-1])
        if inside.any():
            k = np.unique(np.clip(np.searchsorted(tt, t[inside], side="right") - 1, 0, tt.size - 2))
            gaps = ", ".join(f"{tt[j]:.3f} … {tt[j + 1]:.3f} s ({tt[j + 1] - tt[j]:.3f} s)" for j in k[:3])
            more = f" and {k.size - 3} more" if k.size > 3 else ""
            parts.append(f"{int(inside.sum())} in the gap{'s' if k.size > 1 else ''} {gaps}{more}")
        n_nan = int(np.sum(~np.isfinite(t)))
        if n_nan:
            parts.append(f"{n_nan} NaN")
        return "; ".join(parts)

    def check_coverage(self, t_gps_s) -> None:
        t = np.asarray(t_gps_s, dtype=float)
        bad = self.uncovered(t)
        if not bad.any():
            return
        tb = t[bad]
        finite = tb[np.isfinite(tb)]
        msg = (
            f"{self.name} covers t = {self.t_gps_s[0]:.3f} … {self.t_gps_s[-1]:.3f} s "
            f"(gaps > {self.max_gap_s:g} s refused); {bad.sum()} of {t.size} times fall outside"
        )
        if finite.size:
            msg += f": first {finite.min():.3f} s, last {finite.max():.3f} s"
        if finite.size < tb.size:
            msg += f"; {tb.size - finite.size} times are NaN"
        raise TrajectoryError(msg)

    def interpolate(self, t_gps_s) -> Poses:
        """Poses at the given times (see module docstring for the method)."""
        k, w = self.locate(t_gps_s)
        p = self.p_lgf_m[k] + w[:, None] * (self.p_lgf_m[k + 1] - self.p_lgf_m[k])
        R = self.r_b_n[k] @ frames.rotation_from_vector(w[:, None] * self.interval_rotvec[k])
        rpy = np.stack(frames.euler_zyx_from_matrix(R), axis=-1)

        def lerp(a):
            if a is None:
                return None
            return a[k] + w[:, None] * (a[k + 1] - a[k])

        return Poses(p, rpy, R, lerp(self.sigma_p_m), lerp(self.sigma_rpy_rad))

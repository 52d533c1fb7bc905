"""Planar rectangles in the LGF (targets, quay wall, validation planes) and plane fitting.

A rectangle is given by its centre, its width along a horizontal edge, its height along the
slope, its inclination to the horizontal (90° vertical, 0° horizontal facing up) and the azimuth
its normal's horizontal part points to (toward the water). In NED:

    n = [sin i · cos az,  sin i · sin az,  −cos i]      (faces up-and-out for 0 < i < 90°)
    u = [−sin az, cos az, 0]                             (width axis, horizontal)
    v = u × n                                            (height axis, up the slope)

Negative inclinations (the thesis's terrestrial sweep, −90°…90°) tilt the plane the other way.

A vertical cylinder (a pile, a post, a dolphin) is given by the point of its axis at mid-height,
its radius and its height; its surface is ``|(x − c)_h| = r`` for ``|x_D − c_D| ≤ h/2`` (the
subscript h: the north and east components; NED, so "up" is −D).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Rectangle:
    name: str
    center_m: np.ndarray  # (3,) LGF
    normal: np.ndarray  # (3,) unit
    u_axis: np.ndarray  # (3,) unit, width direction
    v_axis: np.ndarray  # (3,) unit, height direction
    width_m: float
    height_m: float
    reflectivity: float = 0.9

    @classmethod
    def from_orientation(
        cls,
        name: str,
        center_m,
        width_m: float,
        height_m: float,
        inclination_rad: float,
        facing_azimuth_rad: float,
        reflectivity: float = 0.9,
    ) -> Rectangle:
        i, az = float(inclination_rad), float(facing_azimuth_rad)
        n = np.array([np.sin(i) * np.cos(az), np.sin(i) * np.sin(az), -np.cos(i)])
        u = np.array([-np.sin(az), np.cos(az), 0.0])
        v = np.cross(u, n)
        return cls(
            name, np.asarray(center_m, float), n, u, v, float(width_m), float(height_m), float(reflectivity)
        )

    @property
    def d(self) -> float:
        """Plane offset: n·x + d = 0 on the plane."""
        return -float(self.normal @ self.center_m)

    @property
    def inclination_rad(self) -> float:
        return float(np.arccos(np.clip(-self.normal[2], -1.0, 1.0)))

    def corners(self) -> np.ndarray:
        """(4, 3) corners, counter-clockwise seen from the facing side."""
        hu, hv = 0.5 * self.width_m * self.u_axis, 0.5 * self.height_m * self.v_axis
        c = self.center_m
        return np.array([c - hu - hv, c + hu - hv, c + hu + hv, c - hu + hv])

    def signed_distance(self, p_m) -> np.ndarray:
        return np.asarray(p_m, float) @ self.normal + self.d

    def local_coordinates(self, p_m) -> np.ndarray:
        """(n, 2) coordinates along the width and height axes relative to the centre."""
        q = np.asarray(p_m, float) - self.center_m
        return np.stack([q @ self.u_axis, q @ self.v_axis], axis=-1)

    def contains(self, p_m, margin_m: float = 0.0) -> np.ndarray:
        """Whether each point's projection falls inside the rectangle (grown by ``margin_m``)."""
        uv = self.local_coordinates(p_m)
        return (np.abs(uv[:, 0]) <= 0.5 * self.width_m + margin_m) & (
            np.abs(uv[:, 1]) <= 0.5 * self.height_m + margin_m
        )

    def translated(self, offset_m) -> Rectangle:
        return Rectangle(
            self.name,
            self.center_m + np.asarray(offset_m, float),
            self.normal,
            self.u_axis,
            self.v_axis,
            self.width_m,
            self.height_m,
            self.reflectivity,
        )


@dataclass(frozen=True, kw_only=True)
class VerticalCylinder:
    """A vertical cylinder in the LGF (module docstring)."""

    name: str
    center_m: np.ndarray  # (3,) the axis at mid-height, LGF
    radius_m: float
    height_m: float
    reflectivity: float = 0.3

    def radial_distance_m(self, p_m) -> np.ndarray:
        """(n,) horizontal distance of points from the axis."""
        q = np.atleast_2d(np.asarray(p_m, float))[:, :2] - self.center_m[:2]
        return np.hypot(q[:, 0], q[:, 1])

    def signed_distance(self, p_m) -> np.ndarray:
        """(n,) distance of points from the surface, positive outside."""
        return self.radial_distance_m(p_m) - self.radius_m

    def outward_normals(self, p_m) -> np.ndarray:
        """(n, 3) the horizontal unit vectors from the axis through the points."""
        q = np.atleast_2d(np.asarray(p_m, float))[:, :2] - self.center_m[:2]
        r = np.hypot(q[:, 0], q[:, 1])[:, None]
        return np.column_stack([q / r, np.zeros(q.shape[0])])

    def translated(self, offset_m) -> VerticalCylinder:
        return VerticalCylinder(
            name=self.name,
            center_m=self.center_m + np.asarray(offset_m, float),
            radius_m=self.radius_m,
            height_m=self.height_m,
            reflectivity=self.reflectivity,
        )


@dataclass(frozen=True)
class PlaneFit:
    """Least-squares plane of a point set (the thesis's Algorithm 1 of Chapter 3)."""

    centroid_m: np.ndarray
    normal: np.ndarray  # unit; eigenvector of the smallest eigenvalue
    d: float
    eigenvalues: np.ndarray  # descending λ1 ≥ λ2 ≥ λ3
    n_points: int

    @property
    def planarity(self) -> float:
        """(λ2 − λ3) / λ1."""
        l1, l2, l3 = self.eigenvalues
        return float((l2 - l3) / l1) if l1 > 0 else 0.0

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(max(self.eigenvalues[2], 0.0)))


def fit_plane(p_m, orient_like=None) -> PlaneFit:
    """Fit a plane by PCA; the normal is flipped to agree with ``orient_like`` when given."""
    p = np.asarray(p_m, float)
    if p.ndim != 2 or p.shape[0] < 3:
        raise ValueError(f"fit_plane needs at least 3 points, got {p.shape[0] if p.ndim == 2 else p.shape}")
    c = p.mean(axis=0)
    q = p - c
    cov = q.T @ q / p.shape[0]
    vals, vecs = np.linalg.eigh(cov)
    n = vecs[:, 0]
    if orient_like is not None and n @ np.asarray(orient_like, float) < 0:
        n = -n
    return PlaneFit(c, n, -float(n @ c), vals[::-1].copy(), p.shape[0])

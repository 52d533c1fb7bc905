"""Ray casting against vertical cylinders (piles, posts, dolphins:
:class:`calib.core.geometry.VerticalCylinder`) and the scan-angle sector a cylinder occupies in a
2D profiler's scan plane (the cylinder counterparts of :class:`calib.sim.scene.Scene`'s
rectangle geometry).

A ray ``x = o + ρ·d`` meets the cylinder's side ``|(x − c)_h| = r`` (subscript h: the north and
east components) where, with ``q = (o − c)_h``,

    a ρ² + 2 b ρ + k = 0,    a = |d_h|²,  b = q·d_h,  k = |q|² − r²,

and a ray from outside enters at the smaller root, computed without cancellation as
``ρ = k / (−b + √(b² − a k))`` when the ray approaches the axis (b < 0). Only that entry counts,
and only when it lies within the cylinder's height: the cylinder is its side (no caps), seen from
outside; a ray passing beside, above or below it (or through an open end) misses it.

The sector of a scan plane (through the scanner, normal ``e_x``) is found as for a rectangle: the
cylinder, grown, is enclosed in a prism on a circumscribed regular polygon; the plane cuts the
prism's edges in a convex polygon that holds every point of the plane on the cylinder, and the
angles of that polygon's vertices seen from the scanner bound every ray that can hit it. A
scanner inside the (grown) prism's circumscribed cylinder gets the full circle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.core.geometry import VerticalCylinder

#: The sides of the polygon the sector's prism is built on.
_PRISM_SIDES = 8
#: Added to a cylinder's radius and half height for its sector (covers rounding; metres).
_SECTOR_MARGIN_M = 1e-6


@dataclass(frozen=True, kw_only=True)
class LeaningCylinder(VerticalCylinder):
    """A pile whose axis leans (the simulator's only: the calibration models vertical
    cylinders): its axis rises through ``center_m`` along (``slope_ne``, −1) in NED, the top
    displaced ``slope_ne`` (north, east) per metre of height; ``height_m`` is the vertical extent
    of its axis (its ends square to the axis)."""

    slope_ne: tuple[float, float] = (0.0, 0.0)

    @property
    def axis_up(self) -> np.ndarray:
        """The axis's unit vector pointing up (NED)."""
        a = np.array([self.slope_ne[0], self.slope_ne[1], -1.0])
        return a / np.linalg.norm(a)

    def radial_distance_m(self, p_m) -> np.ndarray:
        """(n,) distance of points from the (leaning) axis."""
        q = np.atleast_2d(np.asarray(p_m, float)) - self.center_m
        a = self.axis_up
        return np.linalg.norm(q - (q @ a)[:, None] * a, axis=1)

    @property
    def slack_m(self) -> float:
        """How far the axis strays horizontally from the vertical through the centre."""
        return 0.5 * float(self.height_m) * float(np.hypot(*self.slope_ne))

    @property
    def rim_rise_m(self) -> float:
        """How far an end's rim rises above (or sinks below) the axis's end: r·sin(lean)."""
        return float(self.radius_m) * float(np.sqrt(1.0 - self.axis_up[2] ** 2))


@dataclass(frozen=True)
class PackedCylinders:
    """C cylinders as arrays (LGF, metres)."""

    center_m: np.ndarray  # (C, 3) the axis at mid-height
    radius_m: np.ndarray  # (C,) for the sectors: a leaning one's grown by its slack
    half_height_m: np.ndarray  # (C,) a leaning one's grown by its rim's rise
    reflectivity: np.ndarray  # (C,)

    @staticmethod
    def of(cylinders: tuple[VerticalCylinder, ...]) -> PackedCylinders:
        grow = np.array([_lean_growth_m(c) for c in cylinders]).reshape(-1, 2)
        return PackedCylinders(
            center_m=np.array([np.asarray(c.center_m, float) for c in cylinders]).reshape(-1, 3),
            radius_m=np.array([float(c.radius_m) for c in cylinders]) + grow[:, 0],
            half_height_m=np.array([0.5 * float(c.height_m) for c in cylinders]) + grow[:, 1],
            reflectivity=np.array([float(c.reflectivity) for c in cylinders]),
        )


def _lean_growth_m(c: VerticalCylinder) -> tuple[float, float]:
    """How much a cylinder's sector prism grows in radius and half height for its lean."""
    return (c.slack_m, c.rim_rise_m) if isinstance(c, LeaningCylinder) else (0.0, 0.0)


def hit_range(cyl: VerticalCylinder, ox, oy, oz, dx, dy, dz) -> tuple[np.ndarray, np.ndarray]:
    """Range along rays (components, arrays of equal length) to where they enter ``cyl``'s side
    from outside, and whether that entry lies within its height (module docstring). Where a ray
    has no entry (it passes beside the cylinder, or runs parallel to its axis) the range is
    infinite; a ray starting inside gets a negative range (the caller's range limits drop it)."""
    if isinstance(cyl, LeaningCylinder):
        return _leaning_hit_range(cyl, ox, oy, oz, dx, dy, dz)
    c = np.asarray(cyl.center_m, float)
    qx, qy = ox - c[0], oy - c[1]
    a = dx * dx + dy * dy
    b = qx * dx + qy * dy
    k = qx * qx + qy * qy - float(cyl.radius_m) ** 2
    rho, real = _entry(a, b, k)
    up = -(oz + np.where(real, rho, 0.0) * dz - c[2])  # above the mid-height, at the entry
    inside = real & (np.abs(up) <= 0.5 * float(cyl.height_m))
    return rho, inside


def _entry(a, b, k) -> tuple[np.ndarray, np.ndarray]:
    """The smaller root of ``a ρ² + 2 b ρ + k = 0`` (module docstring; infinite where there is
    none) and where there is one."""
    disc = b * b - a * k
    real = (disc >= 0.0) & (a > 0.0)
    root = np.sqrt(np.where(real, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(b < 0.0, k / (root - b), -(b + root) / a)
    return np.where(real, rho, np.inf), real


def _leaning_hit_range(cyl: LeaningCylinder, ox, oy, oz, dx, dy, dz) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hit_range` about a leaning axis ``a``: the components across it, ``q⊥`` and
    ``d⊥``, take the horizontal ones' place, the height is measured along it."""
    c, a = np.asarray(cyl.center_m, float), cyl.axis_up
    q = np.stack([ox - c[0], oy - c[1], oz - c[2]], axis=-1)
    d = np.stack([dx, dy, dz], axis=-1)
    qa, da = q @ a, d @ a
    qp, dp = q - qa[..., None] * a, d - da[..., None] * a
    a2 = np.sum(dp * dp, axis=-1)
    b = np.sum(qp * dp, axis=-1)
    k = np.sum(qp * qp, axis=-1) - float(cyl.radius_m) ** 2
    rho, real = _entry(a2, b, k)
    up = qa + np.where(real, rho, 0.0) * da  # along the axis above the centre, at the entry
    inside = real & (np.abs(up * a[2]) <= 0.5 * float(cyl.height_m))  # the vertical part
    return rho, inside


def local_coordinates(cyl: VerticalCylinder, p_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(arc, up, s) of points (n, 3) on or near ``cyl``: the arc length on its surface from due
    north of its axis, clockwise seen from above (radius × azimuth in (−π, π]), the height above
    its mid-height, and the radial distance beyond its surface."""
    p = np.atleast_2d(np.asarray(p_m, float))
    c = np.asarray(cyl.center_m, float)
    q = p - c
    azimuth = np.arctan2(q[:, 1], q[:, 0])
    return float(cyl.radius_m) * azimuth, -q[:, 2], cyl.signed_distance(p)


def _prism_edges(packed: PackedCylinders, grow_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The end points (C, E, 3) of the edges of each grown cylinder's enclosing prism: the
    vertical edges, then the top and the bottom polygon's edges."""
    n = _PRISM_SIDES
    r = (packed.radius_m + grow_m + _SECTOR_MARGIN_M) / np.cos(np.pi / n)  # circumscribed
    h = packed.half_height_m + grow_m + _SECTOR_MARGIN_M
    ang = 2.0 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=-1)  # (n, 3)
    ring = packed.center_m[:, None, :] + r[:, None, None] * ring  # (C, n, 3) at mid-height
    dz = np.zeros((packed.center_m.shape[0], 1, 3))
    dz[:, 0, 2] = h
    top, bottom = ring - dz, ring + dz  # NED: up is −D
    nxt = np.roll(np.arange(n), -1)
    start = np.concatenate([top, top, bottom], axis=1)
    end = np.concatenate([bottom, top[:, nxt], bottom[:, nxt]], axis=1)
    return start, end


def sectors(
    packed: PackedCylinders, origins_m, axis_x, axis_y, axis_z, grow_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scan-angle sectors ``(start_rad, width_rad, hit)``, each (P, C), of C cylinders for P scan
    planes (the arguments of :meth:`calib.sim.scene.Scene.scan_sectors`), each cylinder grown by
    ``grow_m`` in radius and at both ends (module docstring). A sector covers every scan angle
    whose ray can hit the cylinder; its width is below π, or 2π for a scanner beside the axis."""
    o = np.asarray(origins_m, float)[:, None, None, :]  # (P, 1, 1, 3)
    ex = np.asarray(axis_x, float)[:, None, None, :]
    ey = np.asarray(axis_y, float)[:, None, None, :]
    ez = np.asarray(axis_z, float)[:, None, None, :]
    start, end = _prism_edges(packed, grow_m)
    rel0, rel1 = start[None] - o, end[None] - o  # (P, C, E, 3)
    s0, s1 = np.sum(rel0 * ex, axis=-1), np.sum(rel1 * ex, axis=-1)  # distances to the plane
    crosses = (s0 >= 0) != (s1 >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(crosses, s0 / (s0 - s1), 0.0)
    q = rel0 + f[..., None] * (rel1 - rel0)  # the cut's vertices, from the origin
    y, z = np.sum(q * ey, axis=-1), np.sum(q * ez, axis=-1)
    n_cross = crosses.sum(axis=-1)
    hit = n_cross > 0
    # angles relative to the direction of the vertices' centroid (all within ±π of it)
    cy = np.sum(np.where(crosses, y, 0.0), axis=-1) / np.maximum(n_cross, 1)
    cz = np.sum(np.where(crosses, z, 0.0), axis=-1) / np.maximum(n_cross, 1)
    ref = np.arctan2(cz, cy)
    dev = np.mod(np.arctan2(z, y) - ref[..., None] + np.pi, 2.0 * np.pi) - np.pi
    lo = np.min(np.where(crosses, dev, np.inf), axis=-1, initial=np.inf)
    hi = np.max(np.where(crosses, dev, -np.inf), axis=-1, initial=-np.inf)
    lo, hi = np.where(hit, lo, 0.0), np.where(hit, hi, 0.0)
    start_rad = np.where(hit, np.mod(ref + lo, 2.0 * np.pi), 0.0)
    width_rad = np.where(hit, hi - lo, 0.0)
    # a scanner within the prism's circumscribed cylinder: every angle
    r_out = (packed.radius_m + grow_m + _SECTOR_MARGIN_M) / np.cos(np.pi / _PRISM_SIDES)
    h_out = packed.half_height_m + grow_m + _SECTOR_MARGIN_M
    d = np.asarray(origins_m, float)[:, None, :] - packed.center_m[None]  # (P, C, 3)
    around = (np.hypot(d[..., 0], d[..., 1]) <= r_out) & (np.abs(d[..., 2]) <= h_out)
    return (
        np.where(around, 0.0, start_rad),
        np.where(around, 2.0 * np.pi, width_rad),
        hit | around,
    )

"""A scene of planar rectangles (targets, quay wall, ground, validation planes) and vertical
cylinders (piles, posts, dolphins), and exact, vectorized ray casting against it.

A ray ``x = o + ρ·d`` (``d`` a unit vector) hits rectangle ``j`` at

    ρ_j = n_j·(c_j − o) / (n_j·d),     inside when |u_j·(x − c_j)| ≤ w_j/2 and |v_j·(x − c_j)| ≤ h_j/2

and the nearest hit in ``[min_range, max_range]`` wins; everything else (water, sky) gives no
return. Both faces of a rectangle return. A surface may have a shape (waviness, roughness: a
fixed displacement field along its normal, :mod:`calib.sim.surfaceshape`): its rays then return
the range to the displaced surface, and the rectangle is the surface's mean plane.

A cylinder (:class:`~calib.core.geometry.VerticalCylinder`) returns where a ray enters its side
from outside, within its height (:mod:`calib.sim.cylinders`). Surfaces are numbered rectangles
first (0 … R−1), then cylinders (R … R+C−1); every per-surface quantity (names, kinds,
reflectivity, sectors, hits) follows that numbering. A cylinder is always background: targets
and validation planes are rectangles.

For a 2D profiler the rays of one profile share their origin and lie in one plane, so the
scene also answers the question the simulator asks first: for each scan plane, which sector of
scan angles can hit each surface (:meth:`Scene.scan_sectors`). Only the rays inside a sector
are then tested exactly, which keeps the cost per return independent of the number of
surfaces that are out of view.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from calib.core.geometry import Rectangle, VerticalCylinder
from calib.sim import cylinders as cyl
from calib.sim.surfaceshape import DisplacementField, SurfaceShape

#: Kinds of surfaces; targets and validation planes are reported by name, the others are
#: background (they make the scene realistic and occlude).
BACKGROUND_KINDS = ("wall", "ground", "other")
SURFACE_KINDS = ("target", "validation", *BACKGROUND_KINDS)


@dataclass(frozen=True)
class RayHits:
    """Result of casting n rays."""

    range_m: np.ndarray  # (n,) distance along the ray; NaN where nothing was hit
    surface: np.ndarray  # (n,) int surface index (rectangles, then cylinders); −1 where nothing was hit
    cos_incidence: np.ndarray  # (n,) |n·d| at the hit; NaN where nothing was hit

    @property
    def hit(self) -> np.ndarray:
        return self.surface >= 0


@dataclass(frozen=True)
class ScanSectors:
    """For P scan planes and the S surfaces of a scene (R rectangles, then C cylinders): the scan
    angles ``[start, start + width]`` at which rays of each plane can reach each surface (``hit``
    False: the plane misses it)."""

    start_rad: np.ndarray  # (P, S), in [0, 2π)
    width_rad: np.ndarray  # (P, S), in [0, π]; 2π for a cylinder the scanner stands beside
    hit: np.ndarray  # (P, S) bool


@dataclass(frozen=True)
class Scene:
    """Rectangles and vertical cylinders in the LGF with a kind each (see
    :data:`SURFACE_KINDS`; ``kinds``: the rectangles', then the cylinders', which must be
    background kinds) and optionally a shape for each rectangle (None or an empty tuple: flat)."""

    rectangles: tuple[Rectangle, ...]
    kinds: tuple[str, ...]
    shapes: tuple[SurfaceShape | None, ...] = ()
    cylinders: tuple[VerticalCylinder, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "rectangles", tuple(self.rectangles))
        object.__setattr__(self, "kinds", tuple(self.kinds))
        object.__setattr__(self, "shapes", tuple(self.shapes) or (None,) * len(self.rectangles))
        object.__setattr__(self, "cylinders", tuple(self.cylinders))
        n_rect, n_cyl = len(self.rectangles), len(self.cylinders)
        if len(self.kinds) != n_rect + n_cyl:
            and_cyl = f" and {n_cyl} cylinders" if n_cyl else ""
            raise ValueError(f"Scene: {n_rect} rectangles{and_cyl} but {len(self.kinds)} kinds")
        if len(self.shapes) != n_rect:
            raise ValueError(f"Scene: {n_rect} rectangles but {len(self.shapes)} shapes")
        for name, k in zip(self.names, self.kinds, strict=True):
            if k not in SURFACE_KINDS:
                raise ValueError(
                    f"Scene: surface {name!r} has kind {k!r}, expected one of {', '.join(SURFACE_KINDS)}"
                )
        for c, k in zip(self.cylinders, self.kinds[n_rect:], strict=True):
            if k not in BACKGROUND_KINDS:
                raise ValueError(
                    f"Scene: cylinder {c.name!r} has kind {k!r}; a cylinder is background "
                    f"({', '.join(BACKGROUND_KINDS)})"
                )
        names = self.names
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"Scene: surface names must be unique; repeated: {', '.join(dup)}")

    def __len__(self) -> int:
        return len(self.rectangles) + len(self.cylinders)

    @property
    def names(self) -> list[str]:
        return [r.name for r in self.rectangles] + [c.name for c in self.cylinders]

    def indices(self, kind: str) -> list[int]:
        return [i for i, k in enumerate(self.kinds) if k == kind]

    @property
    def cylinder_indices(self) -> range:
        """The surface indices of the cylinders."""
        return range(len(self.rectangles), len(self))

    def cylinder(self, j: int) -> VerticalCylinder | None:
        """Surface ``j``'s cylinder (None: ``j`` is a rectangle)."""
        k = int(j) - len(self.rectangles)
        return self.cylinders[k] if k >= 0 else None

    def with_rectangles(self, moved: Mapping[int, Rectangle]) -> Scene:
        """The scene with some rectangles replaced (surfaces moved: a hull in the swell), indices,
        kinds, shapes and cylinders kept. A moved surface keeps its name and size, so the
        displacement fields (which depend on nothing else) are shared rather than built again."""
        rects = list(self.rectangles)
        for j, r in moved.items():
            if not 0 <= j < len(rects):
                raise ValueError(f"Scene.with_rectangles: surface {j} is not a rectangle")
            old = rects[j]
            if (r.name, r.width_m, r.height_m) != (old.name, old.width_m, old.height_m):
                raise ValueError(f"Scene.with_rectangles: surface {j} ({old.name!r}) may move, not change")
            rects[j] = r
        out = Scene(tuple(rects), self.kinds, self.shapes, self.cylinders)
        out.__dict__["fields"] = self.fields  # the cached property, filled with the shared fields
        return out

    def subset(self, indices) -> Scene:
        """The scene of surfaces ``indices`` alone (in that order within the rectangles and
        within the cylinders), with their kinds and shapes."""
        n_rect = len(self.rectangles)
        rect = [int(j) for j in indices if int(j) < n_rect]
        cyls = [int(j) for j in indices if int(j) >= n_rect]
        return Scene(
            tuple(self.rectangles[j] for j in rect),
            tuple(self.kinds[j] for j in rect + cyls),
            tuple(self.shapes[j] for j in rect),
            tuple(self.cylinders[j - n_rect] for j in cyls),
        )

    @cached_property
    def fields(self) -> tuple[DisplacementField | None, ...]:
        """Each surface's displacement field (None: flat; a cylinder is)."""
        return tuple(
            None if s is None else s.field(r.name, r.width_m, r.height_m)
            for r, s in zip(self.rectangles, self.shapes, strict=False)
        ) + (None,) * len(self.cylinders)

    # -- packed geometry ----------------------------------------------------------------------

    @cached_property
    def _packed(self) -> dict[str, np.ndarray]:
        """The rectangles' geometry as arrays."""
        rs = self.rectangles
        return {
            "edge": np.array([0.0 if f is None else f.edge_margin_m for f in self.fields[: len(rs)]]),
            "c": np.array([r.center_m for r in rs]).reshape(-1, 3),
            "n": np.array([r.normal for r in rs]).reshape(-1, 3),
            "u": np.array([r.u_axis for r in rs]).reshape(-1, 3),
            "v": np.array([r.v_axis for r in rs]).reshape(-1, 3),
            "hw": np.array([0.5 * r.width_m for r in rs]),
            "hh": np.array([0.5 * r.height_m for r in rs]),
            "refl": np.array([r.reflectivity for r in rs]),
        }

    @cached_property
    def _packed_cylinders(self) -> cyl.PackedCylinders:
        return cyl.PackedCylinders.of(self.cylinders)

    @cached_property
    def reflectivity(self) -> np.ndarray:
        """(S,) each surface's reflectivity."""
        if not self.cylinders:
            return self._packed["refl"]
        return np.concatenate([self._packed["refl"], self._packed_cylinders.reflectivity])

    # -- exact ray casting ----------------------------------------------------------------------

    def hit_range(self, j: int, ox, oy, oz, dx, dy, dz) -> tuple[np.ndarray, np.ndarray]:
        """Range to surface ``j`` along rays given by components (arrays of equal length) and
        whether the hit lies inside the rectangle (range may be negative or infinite: the
        caller applies its range limits). A shaped surface returns the range to its displaced
        surface, inside when the displaced hit is. A cylinder returns the range to where a ray
        enters its side, inside when that lies within its height
        (:func:`calib.sim.cylinders.hit_range`)."""
        c_j = self.cylinder(j)
        if c_j is not None:
            return cyl.hit_range(c_j, ox, oy, oz, dx, dy, dz)
        g = self._packed
        n, c, u, v = g["n"][j], g["c"][j], g["u"][j], g["v"][j]
        den = dx * n[0] + dy * n[1] + dz * n[2]
        num = (c @ n) - (ox * n[0] + oy * n[1] + oz * n[2])
        with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to the plane
            rho = num / den
            # local coordinates of the hit relative to the centre
            qx, qy, qz = ox - c[0] + rho * dx, oy - c[1] + rho * dy, oz - c[2] + rho * dz
            a = qx * u[0] + qy * u[1] + qz * u[2]
            b = qx * v[0] + qy * v[1] + qz * v[2]
        field = self.fields[j]
        if field is None:
            inside = (np.abs(a) <= g["hw"][j]) & (np.abs(b) <= g["hh"][j])
            return rho, inside
        # candidates: plane hits near the rectangle; then the displaced hit decides
        m = g["edge"][j]
        near = np.flatnonzero((np.abs(a) <= g["hw"][j] + m) & (np.abs(b) <= g["hh"][j] + m))
        du = dx[near] * u[0] + dy[near] * u[1] + dz[near] * u[2]
        dv = dx[near] * v[0] + dy[near] * v[1] + dz[near] * v[2]
        a0, b0 = a[near], b[near]
        t = field.solve(a0, b0, den[near], du, dv)
        rho = np.array(rho, dtype=float, copy=True)
        rho[near] += t
        inside = np.zeros(np.shape(rho), bool)
        inside[near] = (np.abs(a0 + t * du) <= g["hw"][j]) & (np.abs(b0 + t * dv) <= g["hh"][j])
        return rho, inside

    def local_coordinates(self, surface, p_lgf_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, b, s) of points: along the width and height axes from the centre of their
        surface (``surface``: an index per point, or one index) and along its normal from its
        mean plane. On a cylinder: the arc length from due north of its axis (clockwise seen
        from above), the height above its mid-height, and the radial distance beyond its side
        (:func:`calib.sim.cylinders.local_coordinates`)."""
        g = self._packed
        p = np.atleast_2d(np.asarray(p_lgf_m, float))
        j = np.broadcast_to(np.asarray(surface, np.int64), p.shape[:1])
        n_rect = len(self.rectangles)
        if not self.cylinders:
            q = p - g["c"][j]
            return (
                np.einsum("ij,ij->i", q, g["u"][j]),
                np.einsum("ij,ij->i", q, g["v"][j]),
                np.einsum("ij,ij->i", q, g["n"][j]),
            )
        out = np.zeros((3, p.shape[0]))
        rect = j < n_rect
        q = p[rect] - g["c"][j[rect]]
        for m, axis in enumerate(("u", "v", "n")):
            out[m, rect] = np.einsum("ij,ij->i", q, g[axis][j[rect]])
        for k in np.unique(j[~rect]):
            s = j == k
            out[:, s] = cyl.local_coordinates(self.cylinders[k - n_rect], p[s])
        return out[0], out[1], out[2]

    def displacement_m(self, surface, p_lgf_m) -> np.ndarray:
        """h(a, b) of each point's surface at the point's (a, b) (0 on a flat surface)."""
        a, b, _ = self.local_coordinates(surface, p_lgf_m)
        j = np.broadcast_to(np.asarray(surface, np.int64), a.shape)
        h = np.zeros(a.shape)
        for k in np.unique(j):
            f = self.fields[k]
            if f is not None:
                s = j == k
                h[s] = f.height_m(a[s], b[s])
        return h

    def distance_m(self, surface, p_lgf_m) -> np.ndarray:
        """Signed distance of points from their (shaped) surface along its normal: 0 for a point
        on it (on a flat surface: the distance from its plane)."""
        _, _, s = self.local_coordinates(surface, p_lgf_m)
        return s - self.displacement_m(surface, p_lgf_m)

    def normals(self, surface, p_lgf_m) -> np.ndarray:
        """(n, 3) unit normals of the surfaces at points on them: the plane's normal, tilted by
        the waviness's slopes on a shaped surface (its roughness is below the beam's footprint);
        on a cylinder the outward radial (horizontal) direction."""
        g = self._packed
        p = np.atleast_2d(np.asarray(p_lgf_m, float))
        j = np.broadcast_to(np.asarray(surface, np.int64), p.shape[:1])
        n_rect = len(self.rectangles)
        if self.cylinders:
            out = np.zeros((p.shape[0], 3))
            rect = j < n_rect
            out[rect] = g["n"][j[rect]]
            for k in np.unique(j[~rect]):
                s = j == k
                out[s] = self.cylinders[k - n_rect].outward_normals(p[s])
        else:
            out = g["n"][j].copy()
        shaped = [k for k in np.unique(j) if self.fields[k] is not None]
        if not shaped:
            return out
        a, b, _ = self.local_coordinates(j, p)
        for k in shaped:
            s = j == k
            f = self.fields[k]
            assert f is not None
            ha, hb = f.waviness_gradient(a[s], b[s])
            nk = g["n"][k] - ha[:, None] * g["u"][k] - hb[:, None] * g["v"][k]
            out[s] = nk / np.linalg.norm(nk, axis=1)[:, None]
        return out

    def intersect(
        self, origins_m, directions, min_range_m: float = 0.0, max_range_m: float = np.inf
    ) -> RayHits:
        """Cast rays (``origins_m`` (n, 3) or (3,), unit ``directions`` (n, 3)); the nearest hit
        with ``min_range_m < ρ ≤ max_range_m`` wins."""
        d = np.atleast_2d(np.asarray(directions, float))
        o = np.broadcast_to(np.asarray(origins_m, float), d.shape)
        n_rays = d.shape[0]
        best = np.full(n_rays, np.inf)
        surf = np.full(n_rays, -1, dtype=np.int64)
        comps = (o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2])
        for j in range(len(self)):
            rho, inside = self.hit_range(j, *comps)
            ok = inside & (rho > min_range_m) & (rho <= max_range_m) & (rho < best)
            best[ok] = rho[ok]
            surf[ok] = j
        hit = surf >= 0
        cos_inc = np.full(n_rays, np.nan)
        x = o[hit] + best[hit, None] * d[hit]
        cos_inc[hit] = np.abs(np.einsum("ij,ij->i", d[hit], self.normals(surf[hit], x)))
        return RayHits(np.where(hit, best, np.nan), surf, cos_inc)

    # -- sectors of scan planes -----------------------------------------------------------------

    def scan_sectors(self, origins_m, axis_x, axis_y, axis_z, grow_m: float = 0.0) -> ScanSectors:
        """Scan-angle sectors of every surface for P scan planes (rectangles here, cylinders by
        :func:`calib.sim.cylinders.sectors`, grown alike: radius and both ends by ``grow_m``).

        Plane p passes through ``origins_m[p]`` with normal ``axis_x[p]``; a scan angle α points
        along ``cos α·axis_y[p] + sin α·axis_z[p]`` (all (P, 3), LGF). Each rectangle is first
        grown by ``grow_m`` on every side, so that rays fired from nearby poses are covered too.
        The sector is the angle the plane's cut through the (grown) rectangle subtends from the
        origin, always less than π. A shaped surface's rectangle is grown further by its
        :attr:`~calib.sim.surfaceshape.DisplacementField.edge_margin_m`.
        """
        rect = self._rectangle_sectors(origins_m, axis_x, axis_y, axis_z, grow_m)
        if not self.cylinders:
            return rect
        start, width, hit = cyl.sectors(self._packed_cylinders, origins_m, axis_x, axis_y, axis_z, grow_m)
        return ScanSectors(
            np.concatenate([rect.start_rad, start], axis=1),
            np.concatenate([rect.width_rad, width], axis=1),
            np.concatenate([rect.hit, hit], axis=1),
        )

    def _rectangle_sectors(self, origins_m, axis_x, axis_y, axis_z, grow_m: float) -> ScanSectors:
        """:meth:`scan_sectors` of the rectangles alone."""
        o = np.asarray(origins_m, float)[:, None, None, :]  # (P, 1, 1, 3)
        ex = np.asarray(axis_x, float)[:, None, None, :]
        ey = np.asarray(axis_y, float)[:, None, None, :]
        ez = np.asarray(axis_z, float)[:, None, None, :]
        g = self._packed
        su = np.array([-1.0, 1.0, 1.0, -1.0])[:, None]  # corner signs, counter-clockwise
        sv = np.array([-1.0, -1.0, 1.0, 1.0])[:, None]
        grow = grow_m + g["edge"]
        corners = (
            g["c"][:, None, :]
            + su * (g["hw"] + grow)[:, None, None] * g["u"][:, None, :]
            + sv * (g["hh"] + grow)[:, None, None] * g["v"][:, None, :]
        )  # (R, 4, 3)
        rel = corners[None] - o  # (P, R, 4, 3)
        s = np.sum(rel * ex, axis=-1)  # signed distances to the scan plane
        s_next = np.roll(s, -1, axis=-1)
        crosses = (s >= 0) != (s_next >= 0)  # an edge the plane cuts: 0 or 2 per rectangle
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(crosses, s / (s - s_next), 0.0)
        q = rel + f[..., None] * (np.roll(rel, -1, axis=-2) - rel)
        ang = np.arctan2(np.sum(q * ez, axis=-1), np.sum(q * ey, axis=-1))  # (P, R, 4)
        first_two = np.argsort(~crosses, axis=-1, kind="stable")[..., :2]
        a = np.take_along_axis(ang, first_two, axis=-1)
        start = np.mod(a[..., 0], 2 * np.pi)
        width = np.mod(a[..., 1] - a[..., 0], 2 * np.pi)
        flip = width > np.pi
        start = np.where(flip, np.mod(a[..., 1], 2 * np.pi), start)
        width = np.where(flip, 2 * np.pi - width, width)
        hit = crosses.any(axis=-1)
        return ScanSectors(np.where(hit, start, 0.0), np.where(hit, width, 0.0), hit)

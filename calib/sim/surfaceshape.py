"""Surface shape: the waviness and roughness of a real wall as a fixed displacement field along
the surface's normal, and where a ray meets the displaced surface.

A shaped surface is its rectangle (centre c, width axis u, height axis v, normal n) displaced
along its normal,

    x(a, b) = c + a·u + b·v + h(a, b)·n,      h = h_wavy + h_rough,    |a| ≤ w/2, |b| ≤ h/2

- **waviness** ``h_wavy``: a sum of :data:`WAVINESS_COMPONENTS` 2-D sinusoids
  ``A_k·sin(k_k·(a, b) + φ_k)``; wavelength ``2π/|k_k|`` drawn log-uniformly in
  ``[λ_min, λ_max]``, one per equal log-stratum so the components span the range; direction and
  phase uniform; amplitude ∝ wavelength (longer waves are higher, as on a real wall). The plane
  ``c0 + c1·a + c2·b`` that fits the sum best over the rectangle is removed, so the rectangle
  stays the surface's least-squares plane (zero mean, no tilt), and the field is scaled so that
  its **RMS over the rectangle** equals ``amplitude_m``;
- **roughness** ``h_rough``: value noise, normal deviates at the nodes of a
  :data:`ROUGHNESS_CELL_M` grid in (a, b), bilinearly interpolated, scaled so that its RMS over
  the surface equals ``roughness_m`` (bilinear weights of unit nodes have mean square (2/3)²,
  so the nodes' sigma is 1.5·``roughness_m``).

Both are fixed properties of the surface, drawn from its *name* (BLAKE2b, never Python's salted
``hash``): the same wall on every run, and every pass sees the same wall — the roughness is the
same at the same place whichever pass looks at it, unlike the scanner's range noise.

A ray ``o + ρ·d`` that meets the mean plane at ``ρ0`` (local ``a0, b0``) meets the displaced
surface at ``ρ0 + t`` with ``t·(n·d) = h(a0 + t·(u·d), b0 + t·(v·d))``: to first order
``t = h/(n·d)``, i.e. ``ρ = ρ_plane + h/cos(incidence)``, refined by Newton steps inside a
bracket (bisection where a step would leave it, near grazing incidence on a rough surface).
A ray counts as a hit when the displaced hit lies within the rectangle; candidates are the rays
whose plane hit lies within the rectangle grown by :attr:`DisplacementField.edge_margin_m`,
which covers every hit up to :data:`MAX_EDGE_INCIDENCE_DEG` incidence.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np

#: Sinusoids summed by the waviness.
WAVINESS_COMPONENTS = 5
#: Node spacing of the roughness field (m): finer than the walls' waviness, about a beam footprint.
ROUGHNESS_CELL_M = 0.03
#: Rays near a shaped surface's edge are found up to this incidence (beyond it, a ray whose
#: plane hit is off the rectangle but whose displaced hit is on it may be missed).
MAX_EDGE_INCIDENCE_DEG = 80.0
#: The search for the displaced hit stops when its steps are below 0.1 pm (Newton: two or three
#: steps; bisections near grazing incidence: at most _MAX_STEPS).
_CONVERGED_M = 1e-13
_MAX_STEPS = 80
#: A normal deviate from a 53-bit uniform is never larger than this (√(−2 ln 2⁻⁵³)).
_MAX_DEVIATE = 8.6
#: The roughness's node deviates are tabulated up to this many nodes (8 bytes each).
_MAX_TABLE_NODES = 4_000_000


@dataclass(frozen=True)
class SurfaceShape:
    """A surface's configured shape (scenario keys ``waviness: {amplitude_m, wavelength_m}``
    and ``roughness_m``): RMS amplitudes in metres, wavelength range [shortest, longest] in
    metres. All zero = flat."""

    waviness_amplitude_m: float = 0.0
    waviness_wavelength_m: tuple[float, float] = (3.0, 8.0)
    roughness_m: float = 0.0

    def __post_init__(self):
        lo, hi = (float(x) for x in self.waviness_wavelength_m)
        object.__setattr__(self, "waviness_wavelength_m", (lo, hi))
        if self.waviness_amplitude_m < 0 or self.roughness_m < 0:
            raise ValueError(f"SurfaceShape: negative amplitude in {self}")
        if not 0 < lo <= hi:
            raise ValueError(f"SurfaceShape: wavelengths must be 0 < shortest ≤ longest, got {lo}, {hi}")

    @property
    def flat(self) -> bool:
        return self.waviness_amplitude_m == 0 and self.roughness_m == 0

    def field(self, name: str, width_m: float, height_m: float) -> DisplacementField | None:
        """The displacement field of the surface ``name`` of this size (None when flat)."""
        if self.flat:
            return None
        return DisplacementField.build(self, name, width_m, height_m)

    def to_dict(self) -> dict:
        return {
            "waviness": {
                "amplitude_m": self.waviness_amplitude_m,
                "wavelength_m": list(self.waviness_wavelength_m),
            },
            "roughness_m": self.roughness_m,
        }


def surface_keys(name: str) -> tuple[int, int]:
    """Two 64-bit keys derived from a surface's name: the waviness's random draws and the
    roughness's hash."""
    digest = hashlib.blake2b(name.encode("utf-8"), digest_size=16, person=b"mls-surface").digest()
    return int.from_bytes(digest[:8], "little"), int.from_bytes(digest[8:], "little")


def _mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 (wrapping arithmetic)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _uniforms(key: int, n: int) -> np.ndarray:
    """n uniforms in [0, 1) drawn from a 64-bit key (SplitMix64: independent of NumPy's
    generators, so a wall keeps its shape across library versions)."""
    with np.errstate(over="ignore"):
        x = _mix(np.uint64(key) + np.arange(1, n + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _node_deviates(key: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """A standard normal deviate for each grid node (i, j), a pure function of (key, i, j)."""
    with np.errstate(over="ignore"):
        h = _mix(np.uint64(key) ^ (i.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)))
        h = _mix(h ^ (j.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)))
        u1 = (_mix(h + np.uint64(1)) >> np.uint64(11)).astype(np.float64) * 2.0**-53
        u2 = (_mix(h + np.uint64(2)) >> np.uint64(11)).astype(np.float64) * 2.0**-53
    return np.sqrt(-2.0 * np.log1p(-u1)) * np.cos(2.0 * np.pi * u2)


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """``h(a, b)`` of one surface (see the module docstring); ``a``, ``b`` in metres along the
    rectangle's width and height axes from its centre, ``h`` in metres along its normal."""

    name: str
    half_width_m: float
    half_height_m: float
    wave_vector_rad_per_m: np.ndarray  # (K, 2) in (a, b)
    phase_rad: np.ndarray  # (K,)
    amplitude_m: np.ndarray  # (K,) after scaling
    trend_m: np.ndarray  # (3,) the scaled plane c0 + c1·a + c2·b that is removed
    roughness_node_sigma_m: float
    roughness_key: int
    waviness_max_m: float  # max |h_wavy| over the rectangle (on the grid that scaled it)
    cell_m: float = ROUGHNESS_CELL_M

    @classmethod
    def build(cls, shape: SurfaceShape, name: str, width_m: float, height_m: float) -> DisplacementField:
        wave_key, rough_key = surface_keys(name)
        hw, hh = 0.5 * float(width_m), 0.5 * float(height_m)
        K = WAVINESS_COMPONENTS
        draw = _uniforms(wave_key, 3 * K).reshape(3, K)
        lo, hi = shape.waviness_wavelength_m
        wavelength = lo * (hi / lo) ** ((np.arange(K) + draw[0]) / K)
        direction = np.pi * draw[1]
        phase = 2.0 * np.pi * draw[2]
        k = (2.0 * np.pi / wavelength)[:, None] * np.column_stack([np.cos(direction), np.sin(direction)])
        amp = wavelength / wavelength.sum()
        trend, wavy_max = np.zeros(3), 0.0
        if shape.waviness_amplitude_m > 0:
            # the least-squares plane and the RMS over the rectangle, on a midpoint grid of
            # λ_min/32 (the midpoint rule's error ~ (2π/32)²/24: 0.2 %)
            na, nb = (int(np.clip(np.ceil(2 * s / (lo / 32)), 16, 1024)) for s in (hw, hh))
            ga = (np.arange(na) + 0.5) / na * 2 * hw - hw
            gb = (np.arange(nb) + 0.5) / nb * 2 * hh - hh
            A, B = (x.ravel() for x in np.meshgrid(ga, gb, indexing="ij"))
            raw = np.sin(np.outer(A, k[:, 0]) + np.outer(B, k[:, 1]) + phase) @ amp
            design = np.column_stack([np.ones_like(A), A, B])
            trend = np.linalg.lstsq(design, raw, rcond=None)[0]
            rest = raw - design @ trend
            rms = float(np.sqrt(np.mean(rest**2)))
            scale = shape.waviness_amplitude_m / rms if rms > 0 else 0.0
            amp, trend, wavy_max = amp * scale, trend * scale, float(np.abs(rest).max() * scale)
        else:
            amp = np.zeros(K)
        return cls(
            name=name,
            half_width_m=hw,
            half_height_m=hh,
            wave_vector_rad_per_m=k,
            phase_rad=phase,
            amplitude_m=amp,
            trend_m=trend,
            roughness_node_sigma_m=1.5 * shape.roughness_m,
            roughness_key=rough_key,
            waviness_max_m=wavy_max,
        )

    # -- the field ----------------------------------------------------------------------------

    @property
    def wavelength_m(self) -> np.ndarray:
        return 2.0 * np.pi / np.linalg.norm(self.wave_vector_rad_per_m, axis=1)

    @property
    def bound_m(self) -> float:
        """An upper bound of |h| over the rectangle: the waviness's maximum on its grid with a
        margin for the grid's spacing (λ_min/32: the maximum between nodes is within 1 %),
        and the largest deviate a node can have."""
        return 1.25 * self.waviness_max_m + _MAX_DEVIATE * self.roughness_node_sigma_m

    @property
    def edge_margin_m(self) -> float:
        """How far outside the rectangle the plane hit of a ray that hits the displaced
        surface can lie (up to :data:`MAX_EDGE_INCIDENCE_DEG` incidence)."""
        return self.bound_m * float(np.tan(np.radians(MAX_EDGE_INCIDENCE_DEG)))

    def _waviness(self, a, b, gradient: bool):
        k = self.wave_vector_rad_per_m
        arg = a[..., None] * k[:, 0] + b[..., None] * k[:, 1] + self.phase_rad
        c0, ca, cb = self.trend_m
        h = np.sin(arg) @ self.amplitude_m - (c0 + ca * a + cb * b)
        if not gradient:
            return h
        c = np.cos(arg) * self.amplitude_m
        return h, c @ k[:, 0] - ca, c @ k[:, 1] - cb

    def waviness_m(self, a_m, b_m) -> np.ndarray:
        return self._waviness(np.asarray(a_m, float), np.asarray(b_m, float), False)

    def waviness_gradient(self, a_m, b_m) -> tuple[np.ndarray, np.ndarray]:
        """(∂h_wavy/∂a, ∂h_wavy/∂b)."""
        _, ga, gb = self._waviness(np.asarray(a_m, float), np.asarray(b_m, float), True)
        return ga, gb

    @cached_property
    def _node_table(self) -> tuple[int, int, np.ndarray] | None:
        """The node deviates over the rectangle grown by the rays' search (hashed once: a
        lookup is several times cheaper than the hash); None when too large."""
        reach = 2.0 * self.edge_margin_m + 2.0 * self.cell_m
        i0, j0 = (int(np.floor(-(h + reach) / self.cell_m)) for h in (self.half_width_m, self.half_height_m))
        ni, nj = (2 * (-k) + 2 for k in (i0, j0))
        if ni * nj > _MAX_TABLE_NODES:
            return None
        i, j = np.meshgrid(np.arange(i0, i0 + ni), np.arange(j0, j0 + nj), indexing="ij")
        return i0, j0, _node_deviates(self.roughness_key, i, j)

    def _deviates(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """The nodes' deviates: from the table where it covers them, else hashed (the same
        values: the table is the hash)."""
        table = self._node_table
        if table is None:
            return _node_deviates(self.roughness_key, i, j)
        i0, j0, z = table
        ii, jj = i - i0, j - j0
        inside = (ii >= 0) & (ii < z.shape[0]) & (jj >= 0) & (jj < z.shape[1])
        if inside.all():
            return z[ii, jj]
        out = _node_deviates(self.roughness_key, i, j)
        out[inside] = z[ii[inside], jj[inside]]
        return out

    def _roughness(self, a, b, gradient: bool):
        s = self.roughness_node_sigma_m
        if s == 0:
            z = np.zeros(np.shape(a))
            return (z, z, z) if gradient else z
        fa, fb = a / self.cell_m, b / self.cell_m
        ia, ib = np.floor(fa), np.floor(fb)
        ta, tb = fa - ia, fb - ib
        i, j = ia.astype(np.int64), ib.astype(np.int64)
        z00, z10 = self._deviates(i, j), self._deviates(i + 1, j)
        z01, z11 = self._deviates(i, j + 1), self._deviates(i + 1, j + 1)
        lo, hi = z00 + ta * (z10 - z00), z01 + ta * (z11 - z01)
        h = s * (lo + tb * (hi - lo))
        if not gradient:
            return h
        ga = s * ((1 - tb) * (z10 - z00) + tb * (z11 - z01)) / self.cell_m
        return h, ga, s * (hi - lo) / self.cell_m

    def roughness_m(self, a_m, b_m) -> np.ndarray:
        return self._roughness(np.asarray(a_m, float), np.asarray(b_m, float), False)

    def height_m(self, a_m, b_m) -> np.ndarray:
        """h(a, b): the displacement along the normal."""
        return self.waviness_m(a_m, b_m) + self.roughness_m(a_m, b_m)

    def _height_and_gradient(self, a, b):
        w, wa, wb = self._waviness(a, b, True)
        r, ra, rb = self._roughness(a, b, True)
        return w + r, wa + ra, wb + rb

    # -- rays -----------------------------------------------------------------------------------

    def solve(self, a0_m, b0_m, dn, du, dv) -> np.ndarray:
        """Range ``t`` to add to the plane hit so that the ray meets the displaced surface, for
        rays meeting the plane at (a0, b0) with direction components (n·d, u·d, v·d), n·d ≠ 0.

        Solves ``G(t) = t·|n·d| − sign(n·d)·h(a0 + t·u·d, b0 + t·v·d) = 0`` from the first-order
        ``t = h/(n·d)`` by Newton steps kept inside a bracket (|h| ≤ L puts the root within
        ±L/|n·d|): a step that leaves it, that does not halve the previous one, or whose slope
        is not positive (a rough surface near grazing incidence) bisects instead (Numerical
        Recipes' ``rtsafe``). Only unconverged rays are iterated."""
        a0, b0 = np.asarray(a0_m, float), np.asarray(b0_m, float)
        dn, du, dv = (np.broadcast_to(np.asarray(x, float), a0.shape) for x in (dn, du, dv))
        sgn, adn = np.sign(dn), np.abs(dn)
        t = self.height_m(a0, b0) / dn  # first order: ρ_plane + h / cos(incidence)
        reach = self._search_bound_m / adn
        lo, hi, last = -reach, reach.copy(), 4.0 * reach  # last: the previous step's length
        active = np.arange(t.size)
        for _ in range(_MAX_STEPS):
            tk, s, n = t[active], sgn[active], adn[active]
            uk, vk = du[active], dv[active]
            h, ha, hb = self._height_and_gradient(a0[active] + tk * uk, b0[active] + tk * vk)
            g = tk * n - s * h
            slope = n - s * (ha * uk + hb * vk)
            lk = np.where(g < 0, tk, lo[active])
            hk = np.where(g < 0, hi[active], tk)
            with np.errstate(divide="ignore", invalid="ignore"):
                newton = tk - g / slope
            # Newton while it stays in the bracket and its steps at least halve (on the
            # roughness's kinks it can bounce between two cells): else bisect
            ok = (slope > 0) & (newton >= lk) & (newton <= hk) & (np.abs(newton - tk) <= 0.5 * last[active])
            new = np.where(ok, newton, 0.5 * (lk + hk))
            lo[active], hi[active], t[active] = lk, hk, new
            last[active] = np.abs(new - tk)
            active = active[last[active] > _CONVERGED_M]
            if active.size == 0:
                break
        return t

    @property
    def _search_bound_m(self) -> float:
        """|h| ≤ this wherever a candidate ray's search goes (the sinusoids' sum, the removed
        plane out to the rectangle grown by twice its edge margin, the largest node deviate),
        doubled for safety."""
        c0, ca, cb = self.trend_m
        reach = 2.0 * self.edge_margin_m
        wavy = np.abs(self.amplitude_m).sum() + abs(c0)
        wavy += abs(ca) * (self.half_width_m + reach) + abs(cb) * (self.half_height_m + reach)
        return 2.0 * float(wavy + _MAX_DEVIATE * self.roughness_node_sigma_m)

"""The harbour front a production survey sails along (:mod:`calib.sim.production`): scenario
:class:`~calib.sim.scenario.Surface` s (rectangles) and :class:`~calib.sim.scenario.Pile` s
(vertical cylinders) in the site frame (``along_m`` along the wall, ``out_m`` from its face toward
the water, ``up_m`` above the scanner, which rides :data:`SCANNER_ABOVE_WATER_M` above the water),
and the swell that moves the moored hulls.

The profiler scans a plane across the track, so a face whose normal points along the track
lies parallel to the scan plane and is never seen; what makes pitch and heading observable are
faces turned part way (normals with along-track *and* across-track components). The quay runs
:data:`QUAY_REACH_M` beyond both ends of the lines and holds:

- the quay wall in two sections, as cast concrete (1 cm RMS waviness over 3–8 m, 1 mm RMS
  roughness; ``wavy_wall``: 4.5 cm over 1.5–6 m, a wall that is not flat), and between them a
  stretch of sloped revetment (33°) that sets the deck edge back, entered by two wing walls
  at 45° (the wall's ends);
- the deck behind it (horizontal, above the scanner: it occludes, it is not seen) and the
  fronts of three warehouses set back on it;
- a low jetty in front of the first section, narrower at its head (deck, head, sides facing
  ±63°);
- round piles (true cylinders) from the water to the deck: a row of 8 in front of the second
  section from 2 m past its wing wall on, 0.5 m clear of the wall, their diameters cycling
  through :data:`PILE_DIAMETERS_M` (0.3–1.2 m) and their spacings through
  :data:`PILE_SPACINGS_M` (5–8 m), and a dolphin standing free in front of the middle of the
  revetment: 4 piles of 0.6 m on a 1.5 m square, its centre 4 m out;
- rubber fenders proud of the first section, boxes 0.45 m proud (front and two side faces), every
  third turned ±30° (set into the wall so that its outermost edge stays 0.45 m proud), and
  bollards on the deck edge (small boxes turned 45°: two faces seen);
- two moored hulls (non-planar clutter): a work boat against the fenders and a barge across the
  basin, each side 5 stations long and 3 strakes high (flare, topsides, bulwark) so that it is
  curved in plan and in section, with a deckhouse (side and raked front);
- optionally (``water``) the water surface, dark (reflectivity 0.02); the simulator has no
  detection threshold, so every downward ray then returns.

117 surfaces: 105 rectangles (106 with ``water``) and 12 cylinders. Feature positions scale with
the line length so that short lines (tests) still pass every kind of feature.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib.core.geometry import Rectangle
from calib.io.bundle import SCANNER_RANGE_M
from calib.sim.scenario import Pile, ProductionSpec, Scenario, Surface
from calib.sim.scene import Scene
from calib.sim.surfaceshape import SurfaceShape

SCANNER_ABOVE_WATER_M = 2.5
WATER_UP_M = -SCANNER_ABOVE_WATER_M
DECK_UP_M = 2.0  # the quay deck, 4.5 m above the water
QUAY_REACH_M = 100.0  # the quay beyond each end of the lines (lines are staggered along it)
WATER_OUT_M = 100.0  # the water surface's reach from the wall (``water``)
WAREHOUSE_SETBACK_M = 25.0
WAREHOUSE_HEIGHT_M = 12.0
REVETMENT_INCLINATION_RAD = float(np.radians(33.0))
QUAY_WALL_SHAPE = SurfaceShape(0.01, (3.0, 8.0), 0.001)
WAVY_WALL_SHAPE = SurfaceShape(0.045, (1.5, 6.0), 0.001)
#: Surfaces of a hull are named ``hull_<hull>_<part>``.
HULL_PREFIX = "hull_"
#: The pile row's diameters and the spacings between consecutive piles, each taken in turn (m).
PILE_DIAMETERS_M = (0.4, 0.6, 0.9, 1.2, 0.3, 0.8)
PILE_SPACINGS_M = (6.0, 7.5, 5.0, 8.0, 6.5)
PILE_CLEARANCE_M = 0.5  # between the wall face and a pile of the row
DOLPHIN_PILE_DIAMETER_M = 0.6
DOLPHIN_SPACING_M = 1.5  # the side of the dolphin's square of piles
DOLPHIN_OUT_M = 4.0  # its centre from the wall line (the revetment's toe)
FENDER_PROUD_M = 0.45

_DEG = float(np.pi / 180.0)


def _vertical(name, kind, along, out, bottom, top, width, facing_deg=0.0, refl=0.3, shape=None) -> Surface:
    """A vertical rectangle from ``bottom`` to ``top`` (up, m)."""
    return Surface(
        name,
        kind,
        along,
        out,
        0.5 * (bottom + top),
        width,
        top - bottom,
        90.0 * _DEG,
        facing_deg * _DEG,
        refl,
        shape,
    )


def _horizontal(name, kind, along0, along1, out0, out1, up, refl=0.3) -> Surface:
    return Surface(
        name,
        kind,
        0.5 * (along0 + along1),
        0.5 * (out0 + out1),
        up,
        abs(along1 - along0),
        abs(out1 - out0),
        0.0,
        0.0,
        refl,
    )


def _fender(name, along, bottom, top, width, turn_deg, refl) -> list[Surface]:
    """A fender: a box ``width`` wide and :data:`FENDER_PROUD_M` deep, turned ``turn_deg`` (its
    front's facing) and set into the wall so that its outermost edge is that far proud; its
    front (named ``name``) and its two side faces (``name_side_a``, ``name_side_b``)."""
    t = turn_deg * _DEG
    hd, hw = 0.5 * FENDER_PROUD_M, 0.5 * width
    out = FENDER_PROUD_M - (hd * np.cos(t) + hw * abs(np.sin(t)))  # the box's centre
    return [
        _vertical(name, "other", along + hd * np.sin(t), out + hd * np.cos(t), bottom, top, width, turn_deg,
                  refl),
        _vertical(f"{name}_side_a", "other", along + hw * np.cos(t), out - hw * np.sin(t), bottom, top,
                  FENDER_PROUD_M, turn_deg + 90.0, refl),
        _vertical(f"{name}_side_b", "other", along - hw * np.cos(t), out + hw * np.sin(t), bottom, top,
                  FENDER_PROUD_M, turn_deg - 90.0, refl),
    ]  # fmt: skip


def _turned_box(name, along, out, size, bottom, top, refl) -> list[Surface]:
    """The two faces seen from the water of a square box turned 45° (a bollard), centred at
    (``along``, ``out``), ``size`` across its sides."""
    r = 0.25 * np.sqrt(2.0) * size  # from the centre to a face's centre, along ±45°
    return [
        _vertical(f"{name}_{tag}", "other", along + r * np.sin(f * _DEG), out + r * np.cos(f * _DEG), bottom, top,
                  size, f, refl)
        for tag, f in (("a", 45.0), ("b", -45.0))
    ]  # fmt: skip


# -- hulls ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Hull:
    """A moored hull: its side seen from the lines, ``stations`` (along from its centre,
    half-breadth) m, ``strakes`` (bottom, top, inclination) from the waterline up, and a
    deckhouse (along from, along to, half-breadth, top). ``side`` +1: the side faces the water
    (moored at the wall), −1: it faces the wall (moored across the basin)."""

    name: str
    along_m: float
    out_m: float  # centreline
    side: int
    stations: tuple[tuple[float, float], ...]
    strakes: tuple[tuple[float, float, float], ...]  # (bottom_up_m, top_up_m, inclination_deg)
    deckhouse: tuple[float, float, float, float]
    reflectivity: float = 0.35

    def surfaces(self) -> list[Surface]:
        out: list[Surface] = []
        s = self.side
        for k, ((x0, b0), (x1, b1)) in enumerate(zip(self.stations[:-1], self.stations[1:], strict=False)):
            length = float(np.hypot(x1 - x0, b1 - b0))
            # the outward normal's horizontal part in (along, out), away from the centreline
            n_along, n_out = -(b1 - b0) / length, s * (x1 - x0) / length
            facing = float(np.arctan2(n_along, n_out))
            offset = 0.0  # outward offset of the strake's bottom edge from the waterline's
            for m, (z0, z1, incl_deg) in enumerate(self.strakes):
                i = incl_deg * _DEG
                run = (z1 - z0) / np.tan(i)  # the top edge lies `run` further in (< 0: out)
                mid = offset - 0.5 * run
                out.append(
                    Surface(
                        f"{HULL_PREFIX}{self.name}_s{k}{m}",
                        "other",
                        self.along_m + 0.5 * (x0 + x1) + mid * n_along,
                        self.out_m + s * 0.5 * (b0 + b1) + mid * n_out,
                        0.5 * (z0 + z1),
                        length,
                        (z1 - z0) / np.sin(i),
                        i,
                        facing,
                        self.reflectivity,
                    )
                )
                offset -= run
        a0, a1, hb, top = self.deckhouse
        deck = self.strakes[-1][1]
        mid = self.along_m + 0.5 * (a0 + a1)
        # the raked front: from the side's fore end forward to the centreline, 1.5 m ahead
        rake = float(np.degrees(np.arctan2(hb, 1.5)))
        out += [
            _vertical(f"{HULL_PREFIX}{self.name}_house_side", "other", mid, self.out_m + s * hb, deck, top, a1 - a0,
                      0.0 if s > 0 else 180.0, 0.6),
            _vertical(f"{HULL_PREFIX}{self.name}_house_front", "other", self.along_m + a1 + 0.75,
                      self.out_m + s * 0.5 * hb, deck, top, float(np.hypot(hb, 1.5)), s * rake if s > 0 else 180.0 - rake,
                      0.6),
        ]  # fmt: skip
        return out


def _hulls(L: float) -> tuple[Hull, ...]:
    w = WATER_UP_M
    boat = Hull(
        "workboat",
        -0.1 * L,
        0.45 + 3.0,  # against the 0.45 m fenders, 6 m beam
        +1,
        ((-12.0, 2.6), (-6.0, 3.0), (0.0, 3.0), (6.0, 2.7), (10.0, 1.8), (12.0, 0.4)),
        ((w, w + 0.5, 100.0), (w + 0.5, w + 1.5, 94.0), (w + 1.5, w + 2.1, 82.0)),
        (-8.0, -1.0, 2.2, w + 4.7),
    )
    barge = Hull(
        "barge",
        0.1 * L,
        75.0,  # its side toward the wall at 70 m
        -1,
        ((-20.0, 4.5), (-12.0, 5.0), (0.0, 5.0), (12.0, 5.0), (17.0, 3.5), (20.0, 1.0)),
        ((w, w + 1.0, 95.0), (w + 1.0, w + 3.0, 91.0), (w + 3.0, w + 4.0, 85.0)),
        (-19.0, -11.0, 4.0, w + 8.0),
    )
    return boat, barge


# -- the harbour ------------------------------------------------------------------------------


def harbour_surfaces(
    line_length_m: float, *, wavy_wall: bool = False, water: bool = False
) -> tuple[Surface, ...]:
    """The harbour front around lines ``line_length_m`` long centred on along = 0 (module
    docstring)."""
    L = float(line_length_m)
    E = 0.5 * L + QUAY_REACH_M  # the quay's ends
    w, d = WATER_UP_M, DECK_UP_M
    wall = WAVY_WALL_SHAPE if wavy_wall else QUAY_WALL_SHAPE
    rev0, rev1 = _revetment(L)
    run = (d - w) / np.tan(REVETMENT_INCLINATION_RAD)  # its horizontal run: the deck edge set back
    wing = run * np.sqrt(2.0)  # the wing walls run back at 45° from the wall's ends to the deck edge
    s: list[Surface] = [
        _vertical("quay_wall_a", "wall", 0.5 * (-E + rev0), 0.0, w, d, rev0 + E, 0.0, 0.25, wall),
        _vertical("quay_wall_b", "wall", 0.5 * (rev1 + E), 0.0, w, d, E - rev1, 0.0, 0.25, wall),
        _vertical("wing_wall_a", "wall", rev0 + 0.5 * run, -0.5 * run, w, d, wing, 45.0, 0.25),
        _vertical("wing_wall_b", "wall", rev1 - 0.5 * run, -0.5 * run, w, d, wing, -45.0, 0.25),
        Surface(
            "revetment", "wall", 0.5 * (rev0 + rev1), -0.5 * run, 0.5 * (w + d), rev1 - rev0 - run,
            (d - w) / np.sin(REVETMENT_INCLINATION_RAD), REVETMENT_INCLINATION_RAD, 0.0, 0.2,
        ),
        _horizontal("deck_a", "ground", -E, rev0, 0.0, -WAREHOUSE_SETBACK_M, d),
        _horizontal("deck_revetment", "ground", rev0 + run, rev1 - run, -run, -WAREHOUSE_SETBACK_M, d),
        _horizontal("deck_b", "ground", rev1, E, 0.0, -WAREHOUSE_SETBACK_M, d),
    ]  # fmt: skip
    # warehouse fronts: three buildings with 15 m between them
    edges = np.linspace(-E + 10.0, E - 10.0, 4)
    for k, (a0, a1) in enumerate(zip(edges[:-1], edges[1:], strict=False)):
        a0, a1 = (a0 + 7.5 if k else a0), (a1 - 7.5 if k < 2 else a1)
        s.append(
            _vertical(f"warehouse_{k}", "wall", 0.5 * (a0 + a1), -WAREHOUSE_SETBACK_M, d, d + WAREHOUSE_HEIGHT_M,
                      a1 - a0, 0.0, 0.35)
        )  # fmt: skip
    # a low jetty 6 m out, 10 m wide at the wall and 4 m at its head, its deck 1.2 m above the water
    xj, jd = -0.3 * L, w + 1.2
    side = float(np.hypot(3.0, 6.0))
    side_deg = float(np.degrees(np.arctan2(6.0, 3.0)))  # its sides' facing: ±63°
    s += [
        _horizontal("jetty_deck", "ground", xj - 2.0, xj + 2.0, 0.0, 6.0, jd, 0.3),
        _vertical("jetty_head", "other", xj, 6.0, w, jd, 4.0, 0.0, 0.3),
        _vertical("jetty_side_a", "other", xj + 3.5, 3.0, w, jd, side, side_deg, 0.3),
        _vertical("jetty_side_b", "other", xj - 3.5, 3.0, w, jd, side, -side_deg, 0.3),
    ]
    # fenders on the first wall section (the work boat lies against some), every third turned
    for k, x in enumerate(np.linspace(-0.45 * L, rev0 - 6.0, 12)):
        turn = (30.0, -30.0)[(k // 3) % 2] if k % 3 == 0 else 0.0
        s += _fender(f"fender_{k}", x, w + 1.0, w + 2.8, 0.4, turn, 0.08)
    # bollards on the deck edge
    for k, x in enumerate(np.linspace(-0.5 * L, 0.5 * L, 10)):
        s += _turned_box(f"bollard_{k}", x, -0.7, 0.35, d, d + 0.5, 0.4)
    for hull in _hulls(L):
        s += hull.surfaces()
    if water:
        s.append(_horizontal("water", "other", -E, E, 0.0, WATER_OUT_M, w, 0.02))
    return tuple(s)


def _revetment(L: float) -> tuple[float, float]:
    """The revetment stretch [rev0, rev1] along the wall line for lines ``L`` m long."""
    rev0 = 0.2 * L
    return rev0, rev0 + float(np.clip(0.2 * L, 20.0, 60.0))


def harbour_piles(line_length_m: float) -> tuple[Pile, ...]:
    """The harbour's piles around lines ``line_length_m`` long (module docstring): the row
    ``pile_<k>`` in front of the second wall section, then the dolphin's ``dolphin_<k>`` in front
    of the revetment, all from the water to the deck."""
    rev0, rev1 = _revetment(float(line_length_m))
    w, d = WATER_UP_M, DECK_UP_M
    out: list[Pile] = []
    x = rev1 + 2.0
    for k in range(8):
        if k:
            x += PILE_SPACINGS_M[(k - 1) % len(PILE_SPACINGS_M)]
        dia = PILE_DIAMETERS_M[k % len(PILE_DIAMETERS_M)]
        out.append(Pile(name=f"pile_{k}", along_m=x, out_m=PILE_CLEARANCE_M + 0.5 * dia, bottom_up_m=w,
                        top_up_m=d, diameter_m=dia, reflectivity=0.3))  # fmt: skip
    xd, h = 0.5 * (rev0 + rev1), 0.5 * DOLPHIN_SPACING_M  # the dolphin's centre
    for k, (da, do) in enumerate(((-h, -h), (h, -h), (h, h), (-h, h))):
        out.append(Pile(name=f"dolphin_{k}", along_m=xd + da, out_m=DOLPHIN_OUT_M + do, bottom_up_m=w,
                        top_up_m=d, diameter_m=DOLPHIN_PILE_DIAMETER_M, reflectivity=0.3))  # fmt: skip
    return tuple(out)


def harbour_scenario(base: Scenario, spec: ProductionSpec) -> Scenario:
    """``base`` as a production survey ``spec`` of the harbour front: its surfaces and piles
    replaced by the harbour's, the profiler recording its full circle up to 119 m at
    ``spec.rate_scale``, turns between lines; mount, truth, noise and the rest of the motion
    kept. (Its passes become the lines when they are laid out:
    :func:`calib.sim.production.sail_production`.)"""
    scanner = replace(
        base.scanner,
        angular_windows_rad=(),
        point_rate_scale=float(spec.rate_scale),
        max_range_m=SCANNER_RANGE_M[1],
    )
    return replace(
        base,
        surfaces=harbour_surfaces(spec.line_length_m, wavy_wall=spec.wavy_wall, water=spec.water),
        piles=harbour_piles(spec.line_length_m),
        scanner=scanner,
        motion=replace(base.motion, turns=True),
        capture_validation_planes=False,
        production=spec,
    )


# -- the swell --------------------------------------------------------------------------------


@dataclass(frozen=True)
class HullSwell:
    """How the moored hulls move: heave (m, + up), sway (m, + toward the water) and roll (rad,
    about the hull's long axis at the waterline) as sinusoids with a phase per hull, plus a
    drift per line (along, out in m, yaw in rad; normal, these sigmas) so that lines see each
    hull in different places."""

    heave_m: float = 0.25
    heave_period_s: float = 7.0
    sway_m: float = 0.2
    sway_period_s: float = 9.0
    roll_rad: float = float(np.radians(3.0))
    roll_period_s: float = 6.0
    drift_sigma: tuple[float, float, float] = field(default=(0.4, 0.25, float(np.radians(0.5))))

    def to_dict(self) -> dict:
        return {
            "heave": {"amplitude_m": self.heave_m, "period_s": self.heave_period_s},
            "sway": {"amplitude_m": self.sway_m, "period_s": self.sway_period_s},
            "roll": {"amplitude_deg": float(np.degrees(self.roll_rad)), "period_s": self.roll_period_s},
            "drift_sigma": {
                "along_m": self.drift_sigma[0],
                "out_m": self.drift_sigma[1],
                "yaw_deg": float(np.degrees(self.drift_sigma[2])),
            },
        }


@dataclass(frozen=True)
class HullGroup:
    """The surfaces of one hull in a scene and the LGF axes it moves about."""

    name: str
    indices: tuple[int, ...]
    pivot_lgf_m: np.ndarray  # centreline at the waterline, mid-length
    along: np.ndarray  # unit vectors (LGF): along the wall, toward the water, up
    out: np.ndarray
    up: np.ndarray


def hull_groups(scenario: Scenario, scene: Scene) -> tuple[HullGroup, ...]:
    """The hulls of a harbour scene (their surfaces found by name)."""
    along = scenario.site_to_lgf(1.0, 0.0, 0.0)[0]
    out = scenario.site_to_lgf(0.0, 1.0, 0.0)[0]
    up = scenario.site_to_lgf(0.0, 0.0, 1.0)[0]
    groups = []
    for hull in _hulls(scenario.production.line_length_m if scenario.production else 350.0):
        prefix = f"{HULL_PREFIX}{hull.name}_"
        idx = tuple(i for i, n in enumerate(scene.names) if n.startswith(prefix))
        if idx:
            pivot = scenario.site_to_lgf(hull.along_m, hull.out_m, WATER_UP_M)[0]
            groups.append(HullGroup(hull.name, idx, pivot, along, out, up))
    return tuple(groups)


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues: the active rotation by ``angle_rad`` about the unit ``axis``."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def moved_hulls(
    scene: Scene,
    groups: tuple[HullGroup, ...],
    swell: HullSwell,
    tau_s: float,
    phases_rad: np.ndarray,
    drift: np.ndarray,
) -> Scene:
    """``scene`` (hulls at rest) with every hull moved rigidly to its pose at ``tau_s`` seconds
    into the survey: hull ``h`` with wave phases ``phases_rad[h]`` (heave, sway, roll) and this
    line's ``drift[h]`` (along, out, yaw)."""
    moved: dict[int, Rectangle] = {}
    for h, g in enumerate(groups):
        ph = phases_rad[h]
        heave = swell.heave_m * np.sin(2 * np.pi * tau_s / swell.heave_period_s + ph[0])
        sway = swell.sway_m * np.sin(2 * np.pi * tau_s / swell.sway_period_s + ph[1])
        roll = swell.roll_rad * np.sin(2 * np.pi * tau_s / swell.roll_period_s + ph[2])
        rot = _rotation(g.up, drift[h, 2]) @ _rotation(g.along, roll)
        shift = drift[h, 0] * g.along + (drift[h, 1] + sway) * g.out + heave * g.up
        for j in g.indices:
            r = scene.rectangles[j]
            moved[j] = Rectangle(
                r.name,
                g.pivot_lgf_m + rot @ (r.center_m - g.pivot_lgf_m) + shift,
                rot @ r.normal,
                rot @ r.u_axis,
                rot @ r.v_axis,
                r.width_m,
                r.height_m,
                r.reflectivity,
            )
    return scene.with_rectangles(moved)

"""Physical effects the baseline model leaves out, each a small object registered by name.

An effect has one strength parameter with a unit, a prior range (the values the diagnosis
searches), the strength at which it is absent (``neutral``), the scenario kinds it acts on
and a physical justification (the README's "Candidate effects" table is built from them).
It acts through hooks, run for drops and depositions alike by the runner functions
here (:func:`release_spin`, :func:`apply_effect_loads` every step; and for depositions
:func:`shake_settled` after a batch):

* :meth:`Effect.shape` changes the chip (warp, rounded edges);
* :meth:`Effect.contact` changes the contact model (friction, restitution, floor);
* :meth:`Effect.release` adds angular velocity at release;
* :meth:`Effect.loads` gives forces and torques on flying chips (air);
* :meth:`Effect.after_batch` acts on a settled pile (vibration taps);
* :meth:`Effect.contact_loads` pulls touching chips together (cohesion).

Strengths are given as ``{name: value}``; :func:`check_effects` validates such a mapping.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError
from chipstack.packing.effect_kinds import EFFECTS

__all__ = [
    "EFFECTS",
    "ContactModel",
    "apply_effect_loads",
    "Effect",
    "EffectSetup",
    "check_effects",
    "contact_model",
    "release_spin",
    "setup_effects",
    "shake_settled",
    "spins_at_release",
    "shaped",
]

AIR_DENSITY_G_MM3 = 1.204e-6  # dry air at 20 C, 1 atm
# Quasi-steady coefficients of a falling plate (Andersen, Pesavento & Wang 2005).
_DRAG_A, _DRAG_B, _LIFT_CT = 1.4, 1.0, 1.2


@dataclass(frozen=True)
class ContactModel:
    """What the contact effects may change.

    friction and restitution: chip-chip and chip-floor coefficients; floor_compliance_mm_n:
    0 for a rigid floor, else the floor's contact compliance (mm/N) with damping ratio
    floor_damping_ratio against the chip's mass.
    """

    friction: float
    restitution: float
    floor_compliance_mm_n: float = 0.0
    floor_damping_ratio: float = 0.3


class Effect:
    """Base class: every hook does nothing. Subclasses set the class attributes."""

    name: str = ""
    parameter: str = ""  # what the strength is
    unit: str = ""
    prior: tuple[float, float] = (0.0, 1.0)
    kinds: tuple[str, ...] = ("drop", "stack", "container")
    justification: str = ""
    # How long a simulation with the effect takes against the baseline's (schedulers
    # submit the long calls first): drop pools of the study's table, 6 CPU s a pool
    # without an effect, 19.4 with air drag, 27.5 with warp (bench_table_cost.py).
    simulation_cost: float = 1.0

    def neutral(self, contact: ContactModel) -> float:
        """The strength at which the effect is absent (the baseline's own value)."""
        return 0.0

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        return shape

    def contact(self, model: ContactModel, strength: float) -> ContactModel:
        return model

    def release(self, unit_draws: np.ndarray, strength: float) -> np.ndarray | None:
        """Extra angular velocity (n, 3) rad/s from standard normal draws (n, 3), or None."""
        return None

    def loads(self, state: FlightState, strength: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Forces (k, 3) g mm/s^2 and torques (k, 3) g mm^2/s^2 on flying chips, or None."""
        return None

    def after_batch(self, world, chips: list[int], strength: float, rng) -> bool:
        """Act on a settled pile; True if chips were set moving (they must settle again)."""
        return False

    def contact_loads(self, world, chips: list[int], strength: float) -> None:
        """Loads between touching chips, applied every step while chips move."""

    def acts_per_step(self) -> bool:
        return False

    def check(self, strength: float, key: str) -> None:
        lo, hi = self.prior
        if not math.isfinite(strength):
            raise InputError(f"{key}: strength must be a finite number, got {strength!r}")
        span = hi - lo
        if not lo - 1e-9 * span <= strength <= hi + 1e-9 * span:
            value = f"{strength:g} {self.unit}".strip()  # a coefficient has no unit
            raise InputError(
                f"{key}: strength {value} is outside the prior range [{lo:g}, {hi:g}] of "
                f"effect {self.name!r} ({self.parameter})"
            )


@dataclass(frozen=True)
class FlightState:
    """Flying chips in the world frame: positions (k, 3) mm, quaternions (k, 4),
    velocities (k, 3) mm/s, angular velocities (k, 3) rad/s, and their shapes and
    masses (g)."""

    positions: np.ndarray
    quaternions: np.ndarray
    velocities: np.ndarray
    angular: np.ndarray
    shapes: tuple[ChipShape, ...]
    masses_g: np.ndarray


class AirDrag(Effect):
    name = "air_drag"
    parameter = "air density over that of still air at 20 C"
    unit = ""
    prior = (0.0, 4.0)
    simulation_cost = 3.2  # its loads, computed every step in flight
    kinds = ("drop", "stack", "container")
    justification = (
        "A plate falling through air feels drag (coefficient 1.4 - cos 2a: 2.4 broadside, "
        "0.4 edge-on), circulatory lift 1.2 sin 2a, the added-mass (Munk) torque that turns it "
        "face-down, and rotational damping: the quasi-steady model of Andersen, Pesavento & "
        "Wang (J. Fluid Mech. 541, 2005). Over 200 mm it costs a 20 mm chip only 2-4 % of its "
        "impact speed but turns a tilted chip by 10-40 deg, so it changes how the chip meets "
        "the floor. Strength 1 is real air; up to 4 covers the 2-D model's uncertainty."
    )

    def acts_per_step(self) -> bool:
        return True

    def loads(self, state: FlightState, strength: float):
        if strength <= 0:
            return None
        rho = AIR_DENSITY_G_MM3 * strength
        normals = _face_normals(state.quaternions)
        v = state.velocities
        speed = np.linalg.norm(v, axis=1)
        area = _plan_areas(state.shapes)
        side = np.sqrt(area)
        vn = np.einsum("ij,ij->i", v, normals)
        sin_a = np.clip(np.abs(vn) / np.maximum(speed, 1e-12), 0.0, 1.0)
        cos_2a = 1.0 - 2.0 * sin_a**2
        sin_2a = 2.0 * sin_a * np.sqrt(1.0 - sin_a**2)
        drag = -0.5 * rho * area * (_DRAG_A - _DRAG_B * cos_2a) * speed
        forces = drag[:, None] * v
        # Lift: the pressure on the face the air meets (along -sign(vn) n), the part of it
        # across the flow.
        push = -np.sign(vn)[:, None] * normals
        across = push - (np.einsum("ij,ij->i", push, v) / np.maximum(speed**2, 1e-12))[:, None] * v
        norm = np.linalg.norm(across, axis=1)
        lift = 0.5 * rho * area * _LIFT_CT * sin_2a * speed**2
        ok = norm > 1e-12
        forces[ok] += (lift[ok] / norm[ok])[:, None] * across[ok]
        # Munk torque (M_a V) x V with added mass only across the plate: that of the disc
        # of equal area, 8/3 rho R^3.
        added = 8.0 / 3.0 * rho * (area / np.pi) ** 1.5
        torques = _cross((added * vn)[:, None] * normals, v)
        # Rotational damping of the plate turning about an in-plane axis: strips moving
        # broadside with drag 2.4, integrated over a square of side a: 2.4/64 rho a^5 w|w|.
        w = state.angular
        w_in_plane = w - np.einsum("ij,ij->i", w, normals)[:, None] * normals
        torques -= (
            (_DRAG_A + _DRAG_B) / 64.0 * rho * side**5 * np.linalg.norm(w_in_plane, axis=1)
        )[:, None] * w_in_plane
        return forces, torques


def _plan_areas(shapes: tuple[ChipShape, ...]) -> np.ndarray:
    """Each chip's outline area (mm^2): computed once when every chip is the same shape
    object (a drop experiment's), as this runs every step in air."""
    first = shapes[0] if shapes else None
    if all(s is first for s in shapes):
        return np.full(len(shapes), first.plan_area_mm2 if first is not None else 0.0)
    return np.array([s.plan_area_mm2 for s in shapes])


def _face_normals(quaternions: np.ndarray) -> np.ndarray:
    """The chips' local z axes in the world frame (k, 3) from quaternions (k, 4) x, y, z,
    w: the third column of the rotation matrix, written out because this runs every
    step of a drop in air and scipy's Rotation costs more than the engine's step."""
    x, y, z, w = quaternions.T
    return np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (k, 3) arrays (np.cross's overhead dominates at k ~ 60)."""
    return np.column_stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ]
    )


class ReleasePerturbation(Effect):
    name = "release_perturbation"
    parameter = "standard deviation of the chip's angular velocity about each axis at release"
    unit = "rad/s"
    prior = (0.0, 30.0)
    justification = (
        "A holder or gripper does not let go of all edges at once: the chip leaves with a "
        "spin, mostly about the edge that lets go last. Extra tilt alone is absorbed by "
        "the refitted release tilt range of the baseline; the spin is what it cannot "
        "reproduce (it turns the chip in yaw and tumbles it in flight). 30 rad/s is a "
        "quarter turn in 50 ms."
    )

    def release(self, unit_draws: np.ndarray, strength: float):
        return None if strength <= 0 else strength * unit_draws


def _prism_outline(shape: ChipShape, effect: str) -> tuple[np.ndarray, float]:
    """The convex outline (n, 2) mm and thickness of a flat convex prism, or a clear
    refusal. What the chip can take is read from its geometry, whatever its kind: one
    convex piece whose corners all lie on its two faces, the top outline above the
    bottom one (a box, a regular or convex random polygon, a box-section beam, a plugin's
    flat triangle); a star, a round fibre or a mesh from a file is refused."""
    half = shape.thickness_mm / 2
    z = shape.vertices[:, 2]
    bottom = shape.vertices[np.isclose(z, -half)][:, :2]
    top = shape.vertices[np.isclose(z, half)][:, :2]
    prism = (
        len(shape.convex_pieces) == 1
        and len(bottom) + len(top) == len(z)
        and len(bottom) == len(top) >= 3
        and np.allclose(np.sort(bottom, axis=0), np.sort(top, axis=0))
    )
    if not prism:
        raise InputError(
            f"effect {effect!r}: supports flat convex chips (a convex outline extruded "
            f"through the thickness), not {shape.kind!r} chips"
        )
    hull = ConvexHull(bottom)
    return bottom[hull.vertices], 2 * half


def _hull_properties(pieces: list[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume (mm^3), centre of mass (3,) and inertia tensor per unit mass about it
    (3, 3) mm^2 of a union of disjoint convex pieces."""
    import trimesh

    volume, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for piece in pieces:
        mesh = trimesh.convex.convex_hull(piece)
        v = float(mesh.volume)
        c = np.asarray(mesh.center_mass)
        inertia = np.asarray(mesh.moment_inertia) / 1.0  # density 1: per unit volume * v
        volume += v
        first += v * c
        # Parallel axis back to the origin.
        second += inertia + v * (np.dot(c, c) * np.eye(3) - np.outer(c, c))
    centre = first / volume
    about_centre = second - volume * (np.dot(centre, centre) * np.eye(3) - np.outer(centre, centre))
    return volume, centre, about_centre / volume


def _shape_from_pieces(shape: ChipShape, pieces: list[np.ndarray], name: str) -> ChipShape:
    """A chip made of convex pieces, centred on its centre of mass, local axes kept (the
    effects below keep the chip's mirror symmetries, so its axes stay principal)."""
    volume, centre, inertia = _hull_properties(pieces)
    pieces = [np.ascontiguousarray(p - centre) for p in pieces]
    points = np.vstack(pieces)
    hull = ConvexHull(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    for p in pieces:
        p.setflags(write=False)
    return dataclasses.replace(
        shape,
        name=name,
        vertices=points[hull.vertices],
        faces=tuple(tuple(int(i) for i in f) for f in _remap(hull)),
        convex_pieces=tuple(pieces),
        volume_mm3=volume,
        inertia_mm2=np.diag(inertia).copy(),
        half_extents=(hi - lo) / 2,
        box_centre=(hi + lo) / 2,
        collision="hull",
    )


def _remap(hull: ConvexHull) -> np.ndarray:
    index = {v: k for k, v in enumerate(hull.vertices)}
    return np.array([[index[i] for i in simplex] for simplex in hull.simplices])


def _inset(outline: np.ndarray, distance: float) -> np.ndarray:
    """A convex counter-clockwise outline moved inwards by ``distance`` (mm)."""
    n = len(outline)
    area = 0.5 * np.sum(
        outline[:, 0] * np.roll(outline[:, 1], -1) - np.roll(outline[:, 0], -1) * outline[:, 1]
    )
    if area < 0:
        outline = outline[::-1]
    lines = []
    for i in range(n):
        a, b = outline[i], outline[(i + 1) % n]
        d = (b - a) / np.linalg.norm(b - a)
        inward = np.array([-d[1], d[0]])
        lines.append((a + distance * inward, d))
    corners = []
    for i in range(n):
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        t = np.linalg.solve(np.column_stack([d1, -d2]), p2 - p1)[0]
        corners.append(p1 + t * d1)
    return np.array(corners)


class EdgeRounding(Effect):
    name = "edge_rounding"
    parameter = "radius of the rounded edges and corners"
    unit = "mm"
    prior = (0.0, 0.9)
    justification = (
        "Shredding and handling crush and wear a chip's edges: real chips have rounded or "
        "chamfered rims, not the sharp box edges of the model. A round rim rolls instead of "
        "catching, so a chip landing on a corner bounces and slides differently. Up to 0.9 mm "
        "for a 2 mm chip (a fully round rim is 1 mm)."
    )

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        if strength <= 0:
            return shape
        outline, thickness = _prism_outline(shape, self.name)
        r = min(strength, 0.45 * thickness)
        inner = _inset(outline, r)
        half = thickness / 2 - r
        # A sphere of radius r swept over the inner prism's corners: its convex hull is the
        # rounded chip (corners sampled at 10 deg in longitude, 5 latitudes).
        lon = np.radians(np.arange(0, 360, 10))
        lat = np.radians([-90, -45, 0, 45, 90])
        ball = np.array(
            [[np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)] for b in lat for a in lon]
        )
        ball = np.unique(np.round(ball, 12), axis=0) * r
        corners = np.array([[x, y, z] for x, y in inner for z in (-half, half)])
        points = (corners[:, None, :] + ball[None, :, :]).reshape(-1, 3)
        points = points[ConvexHull(points).vertices]
        return _shape_from_pieces(shape, [points], f"{shape.name} rounded {r:.3g}")


class Warp(Effect):
    name = "warp"
    parameter = "bow of the chip: rise of its ends above its middle"
    unit = "mm"
    prior = (0.0, 3.0)
    simulation_cost = 4.5  # 8 wedge pieces in a compound collision shape
    justification = (
        "Chips cut from a consolidated laminate relax residual stresses and warp, and "
        "reheated chips curl; a bowed chip rocks on landing and rests on its ends. Modelled "
        "as a cylindrical bend about the chip's width, 8 exact wedge pieces; up to 3 mm "
        "over 20 mm."
    )

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        if strength <= 0:
            return shape
        outline, thickness = _prism_outline(shape, self.name)
        length = float(np.ptp(outline[:, 0]))
        x0 = float(outline[:, 0].min())
        # Radius of the mid-surface whose arc of `length` (the chip is bent, not stretched)
        # rises `strength` at its ends: R (1 - cos(L / 2R)) = h.
        h = strength
        from scipy.optimize import brentq

        radius = brentq(
            lambda r: r * (1 - np.cos(length / (2 * r))) - h, length / np.pi, 1e9 * length
        )
        cuts = np.linspace(x0, x0 + length, 9)
        pieces = []
        for a, b in zip(cuts[:-1], cuts[1:], strict=False):
            strip = _clip_x(outline, a, b)
            corners = np.array(
                [[x, y, z] for x, y in strip for z in (-thickness / 2, thickness / 2)]
            )
            theta = corners[:, 0] / radius
            r = radius - corners[:, 2]
            bent = np.column_stack([r * np.sin(theta), corners[:, 1], radius - r * np.cos(theta)])
            pieces.append(bent)
        return _shape_from_pieces(shape, pieces, f"{shape.name} warped {h:.3g}")


def _clip_x(outline: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The part of a convex outline between x = lo and x = hi (Sutherland-Hodgman)."""

    def clip(points, keep, cross):
        out = []
        for i in range(len(points)):
            p, q = points[i - 1], points[i]
            if keep(q):
                if not keep(p):
                    out.append(cross(p, q))
                out.append(q)
            elif keep(p):
                out.append(cross(p, q))
        return out

    def at(x):
        return lambda p, q: p + (x - p[0]) / (q[0] - p[0]) * (q - p)

    points = clip(list(outline), lambda p: p[0] >= lo - 1e-12, at(lo))
    points = clip(points, lambda p: p[0] <= hi + 1e-12, at(hi))
    return np.array(points)


class _ContactCoefficient(Effect):
    """An effect that sets one coefficient of the contact model (its baseline value is
    the neutral strength)."""

    field: str = ""

    def neutral(self, contact: ContactModel) -> float:
        return getattr(contact, self.field)

    def contact(self, model: ContactModel, strength: float) -> ContactModel:
        return dataclasses.replace(model, **{self.field: strength})


class Friction(_ContactCoefficient):
    name = "friction"
    field = "friction"
    parameter = "Coulomb friction coefficient, chip on chip and chip on floor"
    unit = ""
    prior = (0.1, 1.0)
    justification = (
        "The baseline's 0.5 is an estimate (smooth PA6 about 0.3; textured, glass-rich "
        "edges higher; a belt's rubber 0.6-1). Friction decides how far a landed chip "
        "slides and how steep a pile stands."
    )


class Restitution(_ContactCoefficient):
    name = "restitution"
    field = "restitution"
    parameter = "coefficient of restitution of impacts"
    unit = ""
    prior = (0.0, 0.8)
    justification = (
        "No measured value exists for these chips; a thin plate loses much of its impact "
        "energy to flexural vibration (low restitution), a stiff corner impact little. It "
        "sets how high and how often a chip bounces, so how far it travels."
    )


class CompliantFloor(_ContactCoefficient):
    name = "compliant_floor"
    field = "floor_compliance_mm_n"
    parameter = "contact compliance of the floor (its deflection per newton)"
    unit = "mm/N"
    prior = (0.0, 2.0)
    justification = (
        "A conveyor belt or a rubber mat gives under an impact; the baseline floor is rigid. "
        "A compliant floor lengthens the impact and absorbs energy (damping ratio 0.3, a "
        "typical rubber), so a chip bounces less and turns less. 1 mm/N lets a 1.4 g chip "
        "arriving at 2 m/s sink 2.3 mm."
    )


class Vibration(Effect):
    name = "vibration"
    parameter = "upward speed of each tap given to the whole pile (10 taps after each batch)"
    unit = "mm/s"
    prior = (0.0, 500.0)
    kinds = ("stack", "container")
    justification = (
        "A conveyor or a container on a running machine shakes: taps let chips settle into "
        "denser arrangements (vibrated random packings of spheres reach 0.64 against 0.55 "
        "to 0.60 poured). Each tap launches the pile upwards at this speed (a jolt of the "
        "floor) and lets it settle again; 500 mm/s is a 13 mm hop."
    )

    taps = 10

    def after_batch(self, world, chips: list[int], strength: float, rng) -> bool:
        if strength <= 0 or not chips:
            return False
        for chip in chips:
            world.wake(chip)
            world.set_velocity(chip, np.array([0.0, 0.0, strength]), np.zeros(3))
        return True


class Cohesion(Effect):
    name = "cohesion"
    parameter = "pull-off force at each contact point between chips (sizing, moisture, static)"
    unit = "mN"
    prior = (0.0, 20.0)
    kinds = ("stack", "container")
    justification = (
        "Sizing residues, moisture bridges and static charge make fibres and chips stick: a "
        "cohesive pile stands looser and higher. Modelled as a constant pull along the normal "
        "at every contact point between chips; 13 mN is the weight of one 1.36 g chip."
    )

    def acts_per_step(self) -> bool:
        return True

    def contact_loads(self, world, chips: list[int], strength: float) -> None:
        if strength > 0:
            world.pull_contacts(chips, strength * 1e3)  # mN -> g mm/s^2


@dataclass(frozen=True)
class EffectSetup:
    """What a set of effect strengths does to a simulation before it starts: the contact
    model, the physics section carrying its friction and restitution, and the effects
    that act at every step."""

    contact: ContactModel
    physics: object  # packing.sections.PhysicsSpec
    per_step: tuple[tuple[Effect, float], ...]


def setup_effects(preset, physics, strengths: Mapping[str, float]) -> EffectSetup:
    """The contact model and per-step effects of checked ``strengths``."""
    model = contact_model(preset, physics)
    for name, value in strengths.items():
        model = EFFECTS.get(name).contact(model, value)
    return EffectSetup(
        contact=model,
        physics=dataclasses.replace(
            physics, friction=model.friction, restitution=model.restitution
        ),
        per_step=tuple(
            (EFFECTS.get(name), value)
            for name, value in strengths.items()
            if EFFECTS.get(name).acts_per_step() and value > 0
        ),
    )


def release_spin(strengths: Mapping[str, float], draws: np.ndarray) -> np.ndarray:
    """Every effect's release hook summed (drops and depositions alike): extra angular
    velocity (n, 3) rad/s from standard normal ``draws`` (n, 3); zeros when no effect of
    ``strengths`` spins a chip as it leaves its holder."""
    spin = np.zeros(np.shape(draws))
    for name, value in strengths.items():
        extra = EFFECTS.get(name).release(draws, value)
        if extra is not None:
            spin += extra
    return spin


def spins_at_release(strengths: Mapping[str, float]) -> bool:
    """Whether any effect of ``strengths`` has a release hook (its draws are needed)."""
    return any(type(EFFECTS.get(name)).release is not Effect.release for name in strengths)


def apply_effect_loads(
    world, chips: list[int], per_step: list[tuple[Effect, float]]
) -> tuple[np.ndarray, np.ndarray] | None:
    """Apply, for the next step, every per-step effect's loads on the moving ``chips``:
    pulls between touching chips, and loads on flying chips. Returns the chips'
    positions (k, 3) mm and velocities (k, 3) mm/s when they were read (an effect with
    flight loads), else None."""
    for effect, value in per_step:
        effect.contact_loads(world, chips, value)
    flying = [(e, v) for e, v in per_step if type(e).loads is not Effect.loads]
    if not flying or not chips:
        return None
    pos, quat, vel, ang = world.kinematics(chips)
    state = FlightState(
        pos,
        quat,
        vel,
        ang,
        tuple(world.shape(c) for c in chips),
        np.array([world.mass_g(c) for c in chips]),
    )
    forces, torques = np.zeros((len(chips), 3)), np.zeros((len(chips), 3))
    for effect, value in flying:
        loads = effect.loads(state, value)
        if loads is not None:
            forces += loads[0]
            torques += loads[1]
    world.apply_loads(chips, forces, torques, pos)
    return pos, vel


def shake_settled(world, strengths: Mapping[str, float], rng, settle_all) -> int:
    """Every after-batch hook (vibration taps) on a settled pile: each effect acts up to
    its ``taps`` times on every chip, and ``settle_all(chips)`` settles the pile again
    after each act that set chips moving (it returns the steps taken). Returns the steps
    summed."""
    steps = 0
    for name, value in strengths.items():
        effect = EFFECTS.get(name)
        for _ in range(getattr(effect, "taps", 1)):
            everyone = list(range(world.n_chips))
            if not effect.after_batch(world, everyone, value, rng):
                break
            steps += settle_all(everyone)
    return steps


def contact_model(preset, physics) -> ContactModel:
    """The baseline contact model of a scenario's physics section."""
    return ContactModel(
        friction=physics.friction if physics.friction >= 0 else preset.friction,
        restitution=physics.restitution if physics.restitution >= 0 else preset.restitution,
    )


# The effects' objects; packing/effect_kinds.py registers them by name (in this order).
AIR_DRAG = AirDrag()
RELEASE_PERTURBATION = ReleasePerturbation()
EDGE_ROUNDING = EdgeRounding()
WARP = Warp()
FRICTION = Friction()
RESTITUTION = Restitution()
COMPLIANT_FLOOR = CompliantFloor()
VIBRATION = Vibration()
COHESION = Cohesion()


def check_effects(strengths: Mapping[str, float], kind: str, key: str = "effects") -> dict:
    """Validated ``{name: strength}``: known names, finite values within the prior ranges,
    effects that act on scenarios of this ``kind``."""
    checked = {}
    for name, value in strengths.items():
        effect = EFFECTS.get(name, key=key)
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{key}.{name}: strength must be a number, got {value!r}") from None
        effect.check(value, f"{key}.{name}")
        if kind not in effect.kinds:
            raise InputError(
                f"{key}.{name}: effect acts on {', '.join(effect.kinds)} scenarios, not {kind!r}"
            )
        checked[name] = value
    return checked


def shaped(shape: ChipShape, strengths: Mapping[str, float]) -> ChipShape:
    """The chip with every shape effect applied (in registry order)."""
    for name in EFFECTS:
        if strengths.get(name):
            shape = EFFECTS.get(name).shape(shape, strengths[name])
    return shape

"""The PyBullet session: the only place that talks to the physics engine.

PyBullet behaves best when bodies are about one unit across, so the engine runs in an
internal world of ``MM_PER_UNIT`` millimetres per length unit, grams and seconds. That
scale is applied here, on the way in and on the way out; every public method takes and
returns millimetres.

Choices that make a chip stack right before fast (measured; see the README):

* bodies are plain rigid bodies (``useMaximalCoordinates``), not Featherstone
  multibodies: ten times cheaper per body and they can sleep;
* a 0.5 ms step: a chip at 2 m/s moves 1 mm (half its thickness) per step, so it cannot
  pass through a floor or another chip between two collision checks;
* contact ERP 0.5 (PyBullet: 0.2) removes residual interpenetration in the pile to a few
  hundredths of a millimetre;
* settled chips are frozen (made static, asleep, and out of collision with one another)
  one by one and woken when a moving chip can reach them; see :mod:`packing.deposition`.
"""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from core.errors import SimulationError
from core.schema import PhysicsSpec
from packing.bullet import pybullet
from packing.chipshape import ChipShape
from packing.presets import PhysicsPreset

__all__ = ["MM_PER_UNIT", "GRAVITY_MM_S2", "ChipWorld", "GROUND", "ContactRecord"]

log = logging.getLogger(__name__)

MM_PER_UNIT = 10.0  # the one place where the internal length scale lives
GRAVITY_MM_S2 = 9810.0
GROUND = -1  # chip index used for the floor in contact records
_CONTACT_ERP = 0.5
# Impacts slower than this do not bounce (PyBullet: 0.2 units/s = 2 mm/s here). Without it the
# paper preset's restitution of 1 keeps chips resting on soft contacts vibrating for ever.
RESTITUTION_THRESHOLD_MM_S = 20.0
# Collision groups. Frozen chips and the floor only collide with moving chips: pairs of
# frozen chips never enter the broad phase, which otherwise costs about 0.6 us per chip per
# step in a settled pile (890 us per step for 1,350 frozen chips, 22 us with the filter).
_MOVING, _FROZEN, _FLOOR = 1, 2, 4


@dataclass(frozen=True)
class ContactRecord:
    """Closest-point contacts between chips (and the ground, index ``GROUND``).

    Arrays of length m: chip_a, chip_b (chip indices; chip_b is GROUND for the floor),
    point_a, point_b (m, 3) mm on each surface, normal (m, 3) unit vector on b pointing
    towards a, distance (m,) mm (negative: interpenetration).
    """

    chip_a: np.ndarray
    chip_b: np.ndarray
    point_a: np.ndarray
    point_b: np.ndarray
    normal: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.chip_a)


class ChipWorld:
    """A PyBullet world holding a floor (the conveyor, z = 0) and chips.

    Use as a context manager; the engine session is closed on exit, even after an error.
    """

    def __init__(
        self, preset: PhysicsPreset, numerics: PhysicsSpec, isolated: bool = False
    ) -> None:
        self.preset = preset
        # Isolated chips touch only the floor: many independent drops share one world.
        self.isolated = isolated
        self.numerics = numerics
        self.time_step_s = numerics.time_step_s
        self.friction = numerics.friction if numerics.friction >= 0 else preset.friction
        self.restitution = numerics.restitution if numerics.restitution >= 0 else preset.restitution
        self._client: int | None = None
        self._bodies: list[int] = []  # chip index -> body id
        self._index_of: dict[int, int] = {}
        self._mass: list[float] = []
        self._radius_units: list[float] = []
        self._axis_reach_units: list[np.ndarray] = []
        self._shape_ids: dict[int, tuple[int, ChipShape]] = {}
        self._shapes: list[ChipShape] = []
        self._scratch: tempfile.TemporaryDirectory | None = None
        self._walls: list[int] = []
        self._floor = -1
        self.time_s = 0.0
        self.last_kinetic_energy = np.empty(0)

    # -- session ---------------------------------------------------------------------------
    def __enter__(self) -> ChipWorld:
        self._client = pybullet.connect(pybullet.DIRECT)
        c = self._client
        pybullet.setGravity(0, 0, -GRAVITY_MM_S2 / MM_PER_UNIT, physicsClientId=c)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=self.time_step_s,
            numSolverIterations=self.numerics.solver_iterations,
            deterministicOverlappingPairs=1,
            contactERP=_CONTACT_ERP,
            restitutionVelocityThreshold=RESTITUTION_THRESHOLD_MM_S / MM_PER_UNIT,
            physicsClientId=c,
        )
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
        self._floor = pybullet.createMultiBody(0, plane, physicsClientId=c)
        pybullet.setCollisionFilterGroupMask(self._floor, -1, _FLOOR, _MOVING, physicsClientId=c)
        self._apply_contact_model(self._floor)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._client is not None:
            pybullet.disconnect(physicsClientId=self._client)
            self._client = None
        if self._scratch is not None:
            self._scratch.cleanup()
            self._scratch = None

    @property
    def client(self) -> int:
        if self._client is None:
            raise RuntimeError("ChipWorld used outside its `with` block")
        return self._client

    def _apply_contact_model(self, body: int) -> None:
        p = self.preset
        kwargs: dict[str, float] = dict(
            lateralFriction=self.friction,
            restitution=self.restitution,
            # Bullet combines rolling friction as r_a mu_b + r_b mu_a: this gives a lever
            # arm of exactly rolling_resistance_mm between any two bodies.
            rollingFriction=(
                p.rolling_resistance_mm / MM_PER_UNIT / (2 * self.friction)
                if self.friction > 0
                else 0.0
            ),
            spinningFriction=p.spinning_friction,
            linearDamping=0.0,
            angularDamping=0.0,
        )
        if p.contact_processing_threshold_mm is not None:
            kwargs["contactProcessingThreshold"] = p.contact_processing_threshold_mm / MM_PER_UNIT
        pybullet.changeDynamics(body, -1, physicsClientId=self.client, **kwargs)
        if p.contact_stiffness_per_g is not None and body in self._index_of:
            mass = self._mass[self._index_of[body]]
            pybullet.changeDynamics(
                body,
                -1,
                contactStiffness=p.contact_stiffness_per_g * mass,
                contactDamping=p.contact_damping_per_g * mass,
                physicsClientId=self.client,
            )

    def add_container_wall(
        self, radius_mm: float, height_mm: float, segments: int, thickness_mm: float = 5.0
    ) -> None:
        """A static round wall standing on the floor: ``segments`` flat panels whose inner
        faces touch the circle of ``radius_mm`` (a regular polygon circumscribing it)."""
        c = self.client
        angles = 2 * np.pi * (np.arange(segments) + 0.5) / segments
        half_width = radius_mm * np.tan(np.pi / segments) + thickness_mm  # panels overlap
        centre_radius = radius_mm + thickness_mm / 2
        half = np.array([thickness_mm / 2, half_width, height_mm / 2]) / MM_PER_UNIT
        shape = pybullet.createCollisionShapeArray(
            shapeTypes=[pybullet.GEOM_BOX] * segments,
            halfExtents=[half.tolist()] * segments,
            collisionFramePositions=[
                [
                    centre_radius * np.cos(a) / MM_PER_UNIT,
                    centre_radius * np.sin(a) / MM_PER_UNIT,
                    height_mm / 2 / MM_PER_UNIT,
                ]
                for a in angles
            ],
            collisionFrameOrientations=[
                pybullet.getQuaternionFromEuler([0.0, 0.0, float(a)]) for a in angles
            ],
            physicsClientId=c,
        )
        wall = pybullet.createMultiBody(0, shape, physicsClientId=c)
        pybullet.setCollisionFilterGroupMask(wall, -1, _FLOOR, _MOVING, physicsClientId=c)
        self._apply_contact_model(wall)
        self._walls.append(wall)

    # -- chips -----------------------------------------------------------------------------
    @property
    def n_chips(self) -> int:
        return len(self._bodies)

    def _collision_shape(self, shape: ChipShape) -> int:
        """The PyBullet collision shape of a chip shape (made once per shape)."""
        key = id(shape)
        if key in self._shape_ids:
            return self._shape_ids[key][0]
        c = self.client
        if shape.collision == "box":
            sid = pybullet.createCollisionShape(
                pybullet.GEOM_BOX,
                halfExtents=(shape.half_extents / MM_PER_UNIT).tolist(),
                collisionFramePosition=(shape.box_centre / MM_PER_UNIT).tolist(),
                physicsClientId=c,
            )
        elif shape.collision == "cylinder":
            # PyBullet's cylinder runs along z; the fibre's axis is local x.
            sid = pybullet.createCollisionShape(
                pybullet.GEOM_CYLINDER,
                radius=shape.radius_mm / MM_PER_UNIT,
                height=2 * float(shape.half_extents[0]) / MM_PER_UNIT,
                collisionFrameOrientation=[0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)],
                physicsClientId=c,
            )
        elif len(shape.convex_pieces) == 1:
            sid = pybullet.createCollisionShape(
                pybullet.GEOM_MESH,
                vertices=(shape.convex_pieces[0] / MM_PER_UNIT).tolist(),
                physicsClientId=c,
            )
        else:
            # A compound of convex hulls: PyBullet builds one hull per object of an OBJ file
            # (its API takes no vertex lists for compounds).
            if self._scratch is None:
                self._scratch = tempfile.TemporaryDirectory(prefix="chipstack-shapes-")
            path = os.path.join(self._scratch.name, f"shape{len(self._shape_ids)}.obj")
            lines, offset = [], 0
            for k, piece in enumerate(shape.convex_pieces):
                # Faces matter: PyBullet hulls only the vertices that faces use.
                hull = ConvexHull(piece)
                lines.append(f"o piece{k}")
                lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in piece / MM_PER_UNIT]
                lines += [
                    f"f {a + offset + 1} {b + offset + 1} {c + offset + 1}"
                    for a, b, c in hull.simplices
                ]
                offset += len(piece)
            with open(path, "w") as f:
                f.write("\n".join(lines) + "\n")
            sid = pybullet.createCollisionShape(
                pybullet.GEOM_MESH, fileName=path, physicsClientId=c
            )
        if sid < 0:
            raise SimulationError(f"shape {shape.name!r}: PyBullet refused its collision shape")
        self._shape_ids[key] = (sid, shape)  # the shape is kept alive, so its id stays unique
        return sid

    def _inertia(self, chip: int) -> list[float]:
        shape = self._shapes[chip]
        return (self._mass[chip] * shape.inertia_mm2 / MM_PER_UNIT**2).tolist()

    def add_chip(self, shape: ChipShape, position_mm: np.ndarray, quaternion: np.ndarray) -> int:
        """Add a chip at rest; returns its chip index (0, 1, ... in order of addition)."""
        c = self.client
        collision = self._collision_shape(shape)
        mass = self.preset.chip_mass_g(shape.volume_mm3)
        body = pybullet.createMultiBody(
            mass,
            collision,
            -1,
            (np.asarray(position_mm) / MM_PER_UNIT).tolist(),
            np.asarray(quaternion).tolist(),
            useMaximalCoordinates=True,
            physicsClientId=c,
        )
        index = len(self._bodies)
        self._bodies.append(body)
        self._index_of[body] = index
        self._mass.append(mass)
        self._shapes.append(shape)
        self._radius_units.append(shape.circumradius_mm / MM_PER_UNIT)
        v = shape.vertices
        self._axis_reach_units.append(
            np.array([np.hypot(v[:, (a + 1) % 3], v[:, (a + 2) % 3]).max() for a in range(3)])
            / MM_PER_UNIT
        )
        # The exact principal inertia (PyBullet would take that of the bounding box). The
        # mass goes with it: alone, the inertia zeroes a maximal-coordinates body's mass.
        pybullet.changeDynamics(
            body, -1, mass=mass, localInertiaDiagonal=self._inertia(index), physicsClientId=c
        )
        self._apply_contact_model(body)
        pybullet.changeDynamics(
            body, -1, activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=c
        )
        self._set_group(body, moving=True)
        return index

    def _set_group(self, body: int, moving: bool) -> None:
        if self.isolated:
            group, mask = (_MOVING, _FLOOR) if moving else (_FROZEN, 0)
        else:
            group, mask = (_MOVING, _MOVING | _FROZEN | _FLOOR) if moving else (_FROZEN, _MOVING)
        pybullet.setCollisionFilterGroupMask(body, -1, group, mask, physicsClientId=self.client)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            pybullet.stepSimulation(physicsClientId=self.client)
        self.time_s += n * self.time_step_s

    def max_point_speed_mm_s(self, chip: int) -> float:
        """Upper bound of the speed of any point of the chip (mm/s); see :meth:`states`."""
        return float(self.states([chip])[2][0])

    def states(self, chips: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (k, 3) mm, quaternions (k, 4) and point-speed bounds (k,) mm/s.

        The speed bound is |v| + sum over the local axes k of |w_k| r_k, with r_k the
        largest distance of a corner from axis k (triangle inequality). Raises
        :class:`SimulationError` if the solver produced NaN.
        """
        c = self.client
        bodies = [self._bodies[i] for i in chips]
        poses = [pybullet.getBasePositionAndOrientation(b, physicsClientId=c) for b in bodies]
        velocities = [pybullet.getBaseVelocity(b, physicsClientId=c) for b in bodies]
        positions = np.array([p[0] for p in poses], dtype=float).reshape(-1, 3) * MM_PER_UNIT
        quaternions = np.array([p[1] for p in poses], dtype=float).reshape(-1, 4)
        linear = np.array([v[0] for v in velocities], dtype=float).reshape(-1, 3)
        angular = np.array([v[1] for v in velocities], dtype=float).reshape(-1, 3)
        # Bound each turn about a local axis by the farthest point from that axis (a rod
        # spinning about its own axis moves its surface at w r_rod, not w L / 2), and never
        # above |w| times the circumradius.
        reach = np.array([self._axis_reach_units[i] for i in chips], dtype=float).reshape(-1, 3)
        radius = np.array([self._radius_units[i] for i in chips], dtype=float)
        if len(chips):
            local = Rotation.from_quat(quaternions).inv().apply(angular)
            turning = np.minimum(
                (np.abs(local) * reach).sum(axis=1), np.linalg.norm(angular, axis=1) * radius
            )
        else:
            turning = np.empty(0)
        speed = (np.linalg.norm(linear, axis=1) + turning) * MM_PER_UNIT
        if len(chips):
            # Kinetic energy (g mm^2/s^2) of each chip, read by the physics sanity checks.
            mass = np.array([self._mass[i] for i in chips])
            principal = np.array([self._shapes[i].inertia_mm2 for i in chips]) * mass[:, None]
            self.last_kinetic_energy = 0.5 * mass * np.einsum(
                "ij,ij->i", linear, linear
            ) * MM_PER_UNIT**2 + 0.5 * np.einsum("ij,ij->i", principal, local**2)
        else:
            self.last_kinetic_energy = np.empty(0)
        if not (np.isfinite(speed).all() and np.isfinite(positions).all()):
            bad = [chips[k] for k in np.flatnonzero(~np.isfinite(speed + positions.sum(1)))]
            raise SimulationError(
                f"chips {bad[:10]}: pose or velocity became NaN at t = {self.time_s:.4f} s"
            )
        return positions, quaternions, speed

    def kinematics(self, chips: list[int]) -> tuple[np.ndarray, ...]:
        """Positions (k, 3) mm, quaternions (k, 4), velocities (k, 3) mm/s and angular
        velocities (k, 3) rad/s, in the world frame."""
        c = self.client
        poses = [
            pybullet.getBasePositionAndOrientation(self._bodies[i], physicsClientId=c)
            for i in chips
        ]
        speeds = [pybullet.getBaseVelocity(self._bodies[i], physicsClientId=c) for i in chips]
        return (
            np.array([p[0] for p in poses], dtype=float).reshape(-1, 3) * MM_PER_UNIT,
            np.array([p[1] for p in poses], dtype=float).reshape(-1, 4),
            np.array([v[0] for v in speeds], dtype=float).reshape(-1, 3) * MM_PER_UNIT,
            np.array([v[1] for v in speeds], dtype=float).reshape(-1, 3),
        )

    def set_velocity(self, chip: int, velocity_mm_s: np.ndarray, angular_rad_s: np.ndarray) -> None:
        pybullet.resetBaseVelocity(
            self._bodies[chip],
            (np.asarray(velocity_mm_s, dtype=float) / MM_PER_UNIT).tolist(),
            np.asarray(angular_rad_s, dtype=float).tolist(),
            physicsClientId=self.client,
        )

    def apply_loads(
        self, chips: list[int], forces: np.ndarray, torques: np.ndarray, positions_mm: np.ndarray
    ) -> None:
        """Forces (k, 3) g mm/s^2 through the centres of mass at ``positions_mm`` and
        torques (k, 3) g mm^2/s^2, world frame, for the next step only."""
        c = self.client
        for i, force, torque, at in zip(chips, forces, torques, positions_mm, strict=False):
            body = self._bodies[i]
            pybullet.applyExternalForce(
                body,
                -1,
                (force / MM_PER_UNIT).tolist(),
                (at / MM_PER_UNIT).tolist(),
                pybullet.WORLD_FRAME,
                physicsClientId=c,
            )
            pybullet.applyExternalTorque(
                body,
                -1,
                (torque / MM_PER_UNIT**2).tolist(),
                pybullet.WORLD_FRAME,
                physicsClientId=c,
            )

    def pull_contacts(self, chips: list[int], force: float) -> None:
        """Pull each of ``chips`` towards every chip it touches with ``force`` (g mm/s^2)
        per contact point, along the contact normal (cohesion; floor and walls excluded)."""
        c = self.client
        for chip in chips:
            body = self._bodies[chip]
            for point in pybullet.getContactPoints(bodyA=body, physicsClientId=c):
                if point[2] not in self._index_of:
                    continue
                normal_on_b = np.asarray(point[7])  # from B towards A
                pybullet.applyExternalForce(
                    body,
                    -1,
                    (-force / MM_PER_UNIT * normal_on_b).tolist(),
                    list(point[5]),
                    pybullet.WORLD_FRAME,
                    physicsClientId=c,
                )

    def shape(self, chip: int) -> ChipShape:
        return self._shapes[chip]

    def mass_g(self, chip: int) -> float:
        return self._mass[chip]

    def set_floor_compliance(
        self, compliance_mm_n: float, damping_ratio: float, reference_mass_g: float
    ) -> None:
        """A compliant floor: ``compliance_mm_n`` mm of give per newton (0: rigid), damped
        at ``damping_ratio`` of critical for a chip of ``reference_mass_g``. The chips stay
        rigid, so the floor's values govern the contact."""
        if compliance_mm_n <= 0:
            return
        stiffness = 1e6 / compliance_mm_n  # N/mm -> g/s^2 (the same in every length unit)
        pybullet.changeDynamics(
            self._floor,
            -1,
            contactStiffness=float(stiffness),
            contactDamping=float(2 * damping_ratio * np.sqrt(stiffness * reference_mass_g)),
            physicsClientId=self.client,
        )

    def circumradius_mm(self, chips: list[int]) -> np.ndarray:
        return np.array([self._radius_units[i] for i in chips]) * MM_PER_UNIT

    def freeze(self, chip: int) -> None:
        """Make a chip at rest static and asleep: it supports others but costs nothing."""
        body, c = self._bodies[chip], self.client
        pybullet.changeDynamics(body, -1, mass=0.0, physicsClientId=c)
        pybullet.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        pybullet.changeDynamics(
            body, -1, activationState=pybullet.ACTIVATION_STATE_SLEEP, physicsClientId=c
        )
        self._set_group(body, moving=False)

    def wake(self, chip: int) -> None:
        """Give a frozen chip back its mass (at rest)."""
        body, c = self._bodies[chip], self.client
        pybullet.changeDynamics(
            body,
            -1,
            mass=self._mass[chip],
            localInertiaDiagonal=self._inertia(chip),
            # Awake and never put to sleep by Bullet (after 2 s at rest it would stop
            # updating contacts); freezing is ours to decide.
            activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=c,
        )
        self._set_group(body, moving=True)

    def chips_near(self, chip: int, margin_mm: float) -> list[int]:
        """Chips whose bounding boxes come within ``margin_mm`` of this chip's."""
        c = self.client
        lo, hi = pybullet.getAABB(self._bodies[chip], physicsClientId=c)
        m = margin_mm / MM_PER_UNIT
        found = pybullet.getOverlappingObjects(
            [lo[0] - m, lo[1] - m, lo[2] - m],
            [hi[0] + m, hi[1] + m, hi[2] + m],
            physicsClientId=c,
        )
        index = self._index_of
        return sorted(index[b] for b, _ in (found or ()) if b in index and index[b] != chip)

    def within(self, chip: int, others: list[int], distance_mm: float) -> list[int]:
        """The chips of ``others`` whose surface comes within ``distance_mm`` of ``chip``'s."""
        c, body, reach = self.client, self._bodies[chip], distance_mm / MM_PER_UNIT
        return [
            other
            for other in others
            if pybullet.getClosestPoints(body, self._bodies[other], reach, physicsClientId=c)
        ]

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, 3) mm and quaternions (n, 4) x, y, z, w of all chips."""
        c = self.client
        states = [
            pybullet.getBasePositionAndOrientation(b, physicsClientId=c) for b in self._bodies
        ]
        if not states:
            return np.empty((0, 3)), np.empty((0, 4))
        positions = np.array([s[0] for s in states]) * MM_PER_UNIT
        quaternions = np.array([s[1] for s in states])
        if not np.isfinite(positions).all():
            bad = np.flatnonzero(~np.isfinite(positions).all(axis=1))
            raise SimulationError(f"chips {bad.tolist()[:10]}: NaN position at t = {self.time_s}")
        return positions, quaternions

    def contact_points(self, chip: int) -> list[tuple[int, float]]:
        """Current solver contacts of one chip: (other chip index or GROUND, distance mm)."""
        c = self.client
        points = pybullet.getContactPoints(bodyA=self._bodies[chip], physicsClientId=c)
        return [(self._index_of.get(p[2], GROUND), p[8] * MM_PER_UNIT) for p in points]

    def contacts(self, distance_mm: float) -> ContactRecord:
        """All chip-chip and chip-ground closest points within ``distance_mm``.

        Computed from the geometry on demand (not the solver's cached manifolds, which do
        not exist between frozen chips).
        """
        c = self.client
        reach = distance_mm / MM_PER_UNIT
        rows = []
        for a, body in enumerate(self._bodies):
            for b in self.chips_near(a, distance_mm):
                if b <= a:
                    continue
                rows += [
                    (a, b, pt)
                    for pt in pybullet.getClosestPoints(
                        body, self._bodies[b], reach, physicsClientId=c
                    )
                ]
            rows += [
                (a, GROUND, pt)
                for pt in pybullet.getClosestPoints(body, self._floor, reach, physicsClientId=c)
            ]
        if not rows:
            empty3 = np.empty((0, 3))
            return ContactRecord(
                np.empty(0, int), np.empty(0, int), empty3, empty3, empty3, np.empty(0)
            )
        return ContactRecord(
            chip_a=np.array([r[0] for r in rows], dtype=int),
            chip_b=np.array([r[1] for r in rows], dtype=int),
            point_a=np.array([r[2][5] for r in rows]) * MM_PER_UNIT,
            point_b=np.array([r[2][6] for r in rows]) * MM_PER_UNIT,
            normal=np.array([r[2][7] for r in rows]),
            distance=np.array([r[2][8] for r in rows]) * MM_PER_UNIT,
        )

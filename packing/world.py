"""The PyBullet session: with its parts, the only place that talks to the physics engine.

PyBullet behaves best when bodies are about one unit across, so the engine runs in an
internal world of ``MM_PER_UNIT`` millimetres per length unit, grams and seconds. That
scale is applied here and in this module's parts (``packing/world_*.py``), on the way in
and on the way out; every public method takes and returns millimetres.

Choices that make a chip stack right before fast (measured; see the README):

* bodies are plain rigid bodies (``useMaximalCoordinates``), not Featherstone
  multibodies: ten times cheaper per body and they can sleep;
* a 0.5 ms step: a chip at 2 m/s moves 1 mm (half its thickness) per step, so it cannot
  pass through a floor or another chip between two collision checks;
* contact ERP 0.5 (PyBullet: 0.2) removes residual interpenetration in the pile to a few
  hundredths of a millimetre;
* settled chips are frozen (made static, asleep, and out of collision with one another)
  one by one and woken when a moving chip can reach them; see :mod:`packing.deposition`.

:class:`ChipWorld` holds the floor, the walls and the contact model, and hands the rest to
its parts: :class:`~packing.world_engine.EngineSession` (the connection),
:class:`~packing.world_bodies.CollisionShapes` and :class:`~packing.world_bodies.ChipBodies`
(shapes and the register of chips), :class:`~packing.world_freezing.Freezer` (freezing
and waking), :class:`~packing.world_states.ChipStates` (poses, speeds, energies),
:class:`~packing.world_loads.ChipLoads` (velocities and forces) and
:class:`~packing.world_contacts.ContactQueries` (neighbours and contacts).
"""

from __future__ import annotations

import logging

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.packing.bullet import pybullet
from chipstack.packing.presets import PhysicsPreset
from chipstack.packing.sections import PhysicsSpec
from chipstack.packing.world_bodies import ChipBodies, CollisionShapes
from chipstack.packing.world_contacts import GROUND, ContactQueries, ContactRecord
from chipstack.packing.world_engine import GRAVITY_MM_S2, MM_PER_UNIT, EngineSession
from chipstack.packing.world_freezing import Freezer
from chipstack.packing.world_loads import ChipLoads
from chipstack.packing.world_states import ChipStates

__all__ = ["MM_PER_UNIT", "GRAVITY_MM_S2", "ChipWorld", "GROUND", "ContactRecord"]

log = logging.getLogger(__name__)


class ChipWorld:
    """A PyBullet world holding a floor (the conveyor, z = 0) and chips.

    Use as a context manager; the engine session is closed on exit, even after an error.
    The world builds the floor, the walls and the chips with their contact model, and
    steps time; it hands everything else to its parts (see the module docstring).
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
        self._session = EngineSession()
        self._chips = ChipBodies()
        self._collision_shapes = CollisionShapes(self._session)
        self._freezer = Freezer(self._session, self._chips, isolated)
        self._states = ChipStates(self._session, self._chips)
        self._contacts = ContactQueries(self._session, self._chips)
        self._loads = ChipLoads(self._session, self._chips)
        self._walls: list[int] = []
        self._floor = -1
        self.time_s = 0.0

    # -- session ---------------------------------------------------------------------------
    def __enter__(self) -> ChipWorld:
        c = self._session.connect(self.time_step_s, self.numerics.solver_iterations)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=c)
        self._floor = pybullet.createMultiBody(0, plane, physicsClientId=c)
        self._freezer.fixture(self._floor)
        self._apply_contact_model(self._floor)
        return self

    def __exit__(self, *exc: object) -> None:
        self._session.disconnect()
        self._collision_shapes.close()

    @property
    def client(self) -> int:
        return self._session.client

    def _apply_contact_model(
        self, body: int, chip_mass_g: float | None = None, rolls: bool = True
    ) -> None:
        """Friction, restitution and rolling resistance of a body; contact stiffness too
        for a chip (``chip_mass_g``), when the preset makes contacts soft. Rolling
        resistance only on bodies that can roll (``rolls``: round chips, and the floor and
        walls they roll on): Bullet adds three solver rows to every contact that has it,
        which made the flat chips' reference stack 1.4 times slower per step, for no
        effect on a chip that cannot roll."""
        p = self.preset
        kwargs: dict[str, float] = dict(
            lateralFriction=self.friction,
            restitution=self.restitution,
            # Bullet combines rolling friction as r_a mu_b + r_b mu_a: this gives a lever
            # arm of exactly rolling_resistance_mm between any two bodies that roll.
            rollingFriction=(
                p.rolling_resistance_mm / MM_PER_UNIT / (2 * self.friction)
                if self.friction > 0 and rolls
                else 0.0
            ),
            spinningFriction=p.spinning_friction,
            linearDamping=0.0,
            angularDamping=0.0,
        )
        if p.contact_processing_threshold_mm is not None:
            kwargs["contactProcessingThreshold"] = p.contact_processing_threshold_mm / MM_PER_UNIT
        pybullet.changeDynamics(body, -1, physicsClientId=self.client, **kwargs)
        if p.contact_stiffness_per_g is not None and chip_mass_g is not None:
            pybullet.changeDynamics(
                body,
                -1,
                contactStiffness=p.contact_stiffness_per_g * chip_mass_g,
                contactDamping=p.contact_damping_per_g * chip_mass_g,
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
        self._freezer.fixture(wall)
        self._apply_contact_model(wall)
        self._walls.append(wall)

    def add_side_guides(self, half_width_mm: float) -> None:
        """Two frictionless walls, planes at y = +-``half_width_mm`` facing inwards, along
        the whole belt (guides fixed in the line slide along a moving mat; their friction
        on it is not modelled)."""
        c = self.client
        for side in (1.0, -1.0):
            plane = pybullet.createCollisionShape(
                pybullet.GEOM_PLANE, planeNormal=[0.0, -side, 0.0], physicsClientId=c
            )
            wall = pybullet.createMultiBody(
                0, plane, -1, [0.0, side * half_width_mm / MM_PER_UNIT, 0.0], physicsClientId=c
            )
            self._freezer.fixture(wall)
            self._apply_contact_model(wall)
            pybullet.changeDynamics(
                wall, -1, lateralFriction=0.0, rollingFriction=0.0, physicsClientId=c
            )
            self._walls.append(wall)

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

    def step(self, n: int = 1) -> None:
        step, client = pybullet.stepSimulation, self.client
        for _ in range(n):
            step(client)  # the client positionally: a keyword's parsing costs per step
        self.time_s += n * self.time_step_s

    # -- chips -----------------------------------------------------------------------------
    @property
    def n_chips(self) -> int:
        return len(self._chips)

    def add_chip(self, shape: ChipShape, position_mm: np.ndarray, quaternion: np.ndarray) -> int:
        """Add a chip at rest; returns its chip index (0, 1, ... in order of addition)."""
        c = self.client
        collision = self._collision_shapes.of(shape)
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
        index = self._chips.register(body, mass, shape)
        # The exact principal inertia (PyBullet would take that of the bounding box). The
        # mass goes with it: alone, the inertia zeroes a maximal-coordinates body's mass.
        pybullet.changeDynamics(
            body, -1, mass=mass, localInertiaDiagonal=self._chips.inertia(index), physicsClientId=c
        )
        self._apply_contact_model(body, mass, rolls=shape.collision == "cylinder")
        self._freezer.start_moving(body)
        return index

    def shape(self, chip: int) -> ChipShape:
        return self._chips.shapes[chip]

    def mass_g(self, chip: int) -> float:
        return self._chips.masses[chip]

    def circumradius_mm(self, chips: list[int]) -> np.ndarray:
        return self._chips.circumradius_mm(chips)

    def freeze(self, chip: int) -> None:
        """Make a chip at rest static and asleep: it supports others but costs nothing."""
        self._freezer.freeze(chip)

    def wake(self, chip: int) -> None:
        """Give a frozen chip back its mass (at rest)."""
        self._freezer.wake(chip)

    def retire(self, chip: int) -> None:
        """Take a frozen chip out of the engine for good, keeping its pose (read by
        :meth:`poses`): a mat's chips far behind the pour zone cost nothing at all."""
        position, quaternion = self._states.poses_of([chip])
        body = self._chips.retire(chip, position[0], quaternion[0])
        pybullet.removeBody(body, physicsClientId=self.client)

    def is_retired(self, chip: int) -> bool:
        return chip in self._chips.retired

    # -- motion ----------------------------------------------------------------------------
    @property
    def last_kinetic_energy(self) -> np.ndarray:
        """Kinetic energy (g mm^2/s^2) of the chips of the last :meth:`states` call."""
        return self._states.last_kinetic_energy

    def states(self, chips: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (k, 3) mm, quaternions (k, 4) and point-speed bounds (k,) mm/s; see
        :meth:`packing.world_states.ChipStates.states`."""
        return self._states.states(chips, self.time_s)

    def max_point_speed_mm_s(self, chip: int) -> float:
        """Upper bound of the speed of any point of the chip (mm/s); see :meth:`states`."""
        return float(self.states([chip])[2][0])

    def kinematics(self, chips: list[int]) -> tuple[np.ndarray, ...]:
        """Positions (k, 3) mm, quaternions (k, 4), velocities (k, 3) mm/s and angular
        velocities (k, 3) rad/s, in the world frame."""
        return self._states.kinematics(chips)

    def poses_of(self, chips: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Positions (k, 3) mm and quaternions (k, 4) of chips not retired."""
        return self._states.poses_of(chips)

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, 3) mm and quaternions (n, 4) x, y, z, w of all chips."""
        return self._states.poses(self.time_s)

    def set_velocity(self, chip: int, velocity_mm_s: np.ndarray, angular_rad_s: np.ndarray) -> None:
        self._loads.set_velocity(chip, velocity_mm_s, angular_rad_s)

    def apply_loads(
        self, chips: list[int], forces: np.ndarray, torques: np.ndarray, positions_mm: np.ndarray
    ) -> None:
        """Forces (k, 3) g mm/s^2 through the centres of mass at ``positions_mm`` and
        torques (k, 3) g mm^2/s^2, world frame, for the next step only."""
        self._loads.apply_loads(chips, forces, torques, positions_mm)

    def pull_contacts(self, chips: list[int], force: float) -> None:
        """Pull each of ``chips`` towards every chip it touches with ``force`` (g mm/s^2)
        per contact point, along the contact normal (cohesion; floor and walls excluded)."""
        self._loads.pull_contacts(chips, force)

    # -- contacts --------------------------------------------------------------------------
    def chips_near(self, chip: int, margin_mm: float) -> list[int]:
        """Chips whose bounding boxes come within ``margin_mm`` of this chip's."""
        return self._contacts.chips_near(chip, margin_mm)

    def within(self, chip: int, others: list[int], distance_mm: float) -> list[int]:
        """The chips of ``others`` whose surface comes within ``distance_mm`` of ``chip``'s."""
        return self._contacts.within(chip, others, distance_mm)

    def contact_points(self, chip: int) -> list[tuple[int, float]]:
        """Current solver contacts of one chip: (other chip index or GROUND, distance mm)."""
        return self._contacts.contact_points(chip)

    def contacts(self, distance_mm: float) -> ContactRecord:
        """All chip-chip and chip-ground closest points within ``distance_mm``, from the
        geometry (frozen chips have no solver contacts between them)."""
        return self._contacts.closest_points(distance_mm, self._floor)

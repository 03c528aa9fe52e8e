"""Loads on the chips of a :class:`packing.world.ChipWorld`: velocities set, external
forces and torques for the next step, and cohesive pulls between touching chips."""

from __future__ import annotations

import numpy as np

from chipstack.packing.bullet import pybullet
from chipstack.packing.world_bodies import ChipBodies
from chipstack.packing.world_engine import MM_PER_UNIT, EngineSession

__all__ = ["ChipLoads"]


class ChipLoads:
    """Pushes chips, in millimetres, grams and seconds."""

    def __init__(self, session: EngineSession, chips: ChipBodies) -> None:
        self._session = session
        self._chips = chips

    def set_velocity(self, chip: int, velocity_mm_s: np.ndarray, angular_rad_s: np.ndarray) -> None:
        pybullet.resetBaseVelocity(
            self._chips.body_ids[chip],
            (np.asarray(velocity_mm_s, dtype=float) / MM_PER_UNIT).tolist(),
            np.asarray(angular_rad_s, dtype=float).tolist(),
            physicsClientId=self._session.client,
        )

    def apply_loads(
        self, chips: list[int], forces: np.ndarray, torques: np.ndarray, positions_mm: np.ndarray
    ) -> None:
        """Forces (k, 3) g mm/s^2 through the centres of mass at ``positions_mm`` and
        torques (k, 3) g mm^2/s^2, world frame, for the next step only."""
        c = self._session.client
        # One conversion to lists for all chips: per-chip numpy-to-list calls cost more
        # than the engine's step when many chips are in flight.
        forces = (np.asarray(forces, dtype=float) / MM_PER_UNIT).tolist()
        torques = (np.asarray(torques, dtype=float) / MM_PER_UNIT**2).tolist()
        positions = (np.asarray(positions_mm, dtype=float) / MM_PER_UNIT).tolist()
        frame = pybullet.WORLD_FRAME
        ids = self._chips.body_ids
        push, turn = pybullet.applyExternalForce, pybullet.applyExternalTorque
        # The client id positionally: parsing it as a keyword costs a third of each call.
        for i, force, torque, at in zip(chips, forces, torques, positions, strict=False):
            push(ids[i], -1, force, at, frame, c)
            turn(ids[i], -1, torque, frame, c)

    def pull_contacts(self, chips: list[int], force: float) -> None:
        """Pull each of ``chips`` towards every chip it touches with ``force`` (g mm/s^2)
        per contact point, along the contact normal (cohesion; floor and walls excluded)."""
        c = self._session.client
        for chip in chips:
            body = self._chips.body_ids[chip]
            for point in pybullet.getContactPoints(bodyA=body, physicsClientId=c):
                if not self._chips.is_chip(point[2]):
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

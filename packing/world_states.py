"""Reading the motion of the chips of a :class:`packing.world.ChipWorld` out of the
engine, in millimetres: poses, velocities, point-speed bounds and kinetic energies, with
a check that the solver has not produced NaN."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.core.errors import SimulationError
from chipstack.packing.bullet import pybullet
from chipstack.packing.world_bodies import RETIRED, ChipBodies
from chipstack.packing.world_engine import MM_PER_UNIT, EngineSession

__all__ = ["ChipStates"]


class ChipStates:
    """Poses and velocities of chips; :meth:`states` also keeps their kinetic energy in
    ``last_kinetic_energy`` (g mm^2/s^2), for the physics sanity checks."""

    def __init__(self, session: EngineSession, chips: ChipBodies) -> None:
        self._session = session
        self._chips = chips
        self.last_kinetic_energy = np.empty(0)

    def states(self, chips: list[int], time_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (k, 3) mm, quaternions (k, 4) and point-speed bounds (k,) mm/s.

        The speed bound is |v| + sum over the local axes k of |w_k| r_k, with r_k the
        largest distance of a corner from axis k (triangle inequality). Raises
        :class:`SimulationError` if the solver produced NaN (``time_s`` goes in the message).
        """
        positions, quaternions, linear, angular = self._read(chips)
        local = Rotation.from_quat(quaternions).inv().apply(angular) if len(chips) else None
        speed = self._speed_bound(chips, linear, angular, local)
        self.last_kinetic_energy = self._kinetic_energy(chips, linear, local)
        if not (np.isfinite(speed).all() and np.isfinite(positions).all()):
            bad = [chips[k] for k in np.flatnonzero(~np.isfinite(speed + positions.sum(1)))]
            raise SimulationError(
                f"chips {bad[:10]}: pose or velocity became NaN at t = {time_s:.4f} s"
            )
        return positions, quaternions, speed

    def kinematics(self, chips: list[int]) -> tuple[np.ndarray, ...]:
        """Positions (k, 3) mm, quaternions (k, 4), velocities (k, 3) mm/s and angular
        velocities (k, 3) rad/s, in the world frame."""
        positions, quaternions, linear, angular = self._read(chips)
        return positions, quaternions, linear * MM_PER_UNIT, angular

    def poses(self, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, 3) mm and quaternions (n, 4) x, y, z, w of all chips."""
        c = self._session.client
        retired = self._chips.retired
        states = [
            (np.asarray(retired[k][0]) / MM_PER_UNIT, retired[k][1])
            if b == RETIRED
            else pybullet.getBasePositionAndOrientation(b, physicsClientId=c)
            for k, b in enumerate(self._chips.body_ids)
        ]
        if not states:
            return np.empty((0, 3)), np.empty((0, 4))
        positions = np.array([s[0] for s in states]) * MM_PER_UNIT
        quaternions = np.array([s[1] for s in states])
        if not np.isfinite(positions).all():
            bad = np.flatnonzero(~np.isfinite(positions).all(axis=1))
            raise SimulationError(f"chips {bad.tolist()[:10]}: NaN position at t = {time_s}")
        return positions, quaternions

    def poses_of(self, chips: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Positions (k, 3) mm and quaternions (k, 4) of chips still in the engine."""
        c = self._session.client
        poses = [
            pybullet.getBasePositionAndOrientation(self._chips.body_ids[i], physicsClientId=c)
            for i in chips
        ]
        return (
            np.array([p[0] for p in poses], dtype=float).reshape(-1, 3) * MM_PER_UNIT,
            np.array([p[1] for p in poses], dtype=float).reshape(-1, 4),
        )

    def _read(self, chips: list[int]) -> tuple[np.ndarray, ...]:
        """Positions (k, 3) mm, quaternions (k, 4), and the velocities (k, 3) and angular
        velocities (k, 3) in engine units."""
        c = self._session.client
        ids = self._chips.body_ids
        pose, velocity = pybullet.getBasePositionAndOrientation, pybullet.getBaseVelocity
        # Runs every step of a drop in air: one flat list, one array.
        flat: list[float] = []
        for i in chips:
            # The client id positionally: the keyword's parsing costs a third of a read.
            position, quaternion = pose(ids[i], c)
            linear, angular = velocity(ids[i], c)
            flat += position
            flat += quaternion
            flat += linear
            flat += angular
        state = np.array(flat, dtype=float).reshape(-1, 13)
        return state[:, :3] * MM_PER_UNIT, state[:, 3:7], state[:, 7:10], state[:, 10:13]

    def _speed_bound(
        self, chips: list[int], linear: np.ndarray, angular: np.ndarray, local: np.ndarray | None
    ) -> np.ndarray:
        """|v| + the fastest a turn can move a point, mm/s (``local``: the angular
        velocities in the chips' frames)."""
        if local is None:
            turning = np.empty(0)
        else:
            # Bound each turn about a local axis by the farthest point from that axis (a rod
            # spinning about its own axis moves its surface at w r_rod, not w L / 2), and
            # never above |w| times the circumradius.
            reach = np.array([self._chips.axis_reach_units[i] for i in chips], dtype=float).reshape(
                -1, 3
            )
            radius = np.array([self._chips.radius_units[i] for i in chips], dtype=float)
            turning = np.minimum(
                (np.abs(local) * reach).sum(axis=1), np.linalg.norm(angular, axis=1) * radius
            )
        return (np.linalg.norm(linear, axis=1) + turning) * MM_PER_UNIT

    def _kinetic_energy(
        self, chips: list[int], linear: np.ndarray, local: np.ndarray | None
    ) -> np.ndarray:
        """Translational plus rotational kinetic energy of each chip, g mm^2/s^2."""
        if local is None:
            return np.empty(0)
        mass = np.array([self._chips.masses[i] for i in chips])
        principal = np.array([self._chips.shapes[i].inertia_mm2 for i in chips]) * mass[:, None]
        return 0.5 * mass * np.einsum(
            "ij,ij->i", linear, linear
        ) * MM_PER_UNIT**2 + 0.5 * np.einsum("ij,ij->i", principal, local**2)

"""Freezing and waking the chips of a :class:`packing.world.ChipWorld`.

A settled chip is frozen: static (mass 0), asleep, and in a collision group that only
moving chips collide with, so it supports others but costs the solver nothing. A frozen
chip that a moving one can reach is woken: its mass given back, in the moving group.
"""

from __future__ import annotations

from chipstack.packing.bullet import pybullet
from chipstack.packing.world_bodies import ChipBodies
from chipstack.packing.world_engine import EngineSession

__all__ = ["Freezer"]

# Collision groups. Frozen chips and the floor only collide with moving chips: pairs of
# frozen chips never enter the broad phase, which otherwise costs about 0.6 us per chip per
# step in a settled pile (890 us per step for 1,350 frozen chips, 22 us with the filter).
_MOVING, _FROZEN, _FLOOR = 1, 2, 4


class Freezer:
    """Puts chips to rest and wakes them; ``isolated`` chips touch only the floor."""

    def __init__(self, session: EngineSession, chips: ChipBodies, isolated: bool) -> None:
        self._session = session
        self._chips = chips
        self._isolated = isolated

    def fixture(self, body: int) -> None:
        """Put a static body (the floor, a wall) where only moving chips meet it."""
        pybullet.setCollisionFilterGroupMask(
            body, -1, _FLOOR, _MOVING, physicsClientId=self._session.client
        )

    def start_moving(self, body: int) -> None:
        """A new chip: awake, and never put to sleep by Bullet (freezing is ours to decide)."""
        pybullet.changeDynamics(
            body,
            -1,
            activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=self._session.client,
        )
        self._set_group(body, moving=True)

    def freeze(self, chip: int) -> None:
        """Make a chip at rest static and asleep: it supports others but costs nothing."""
        body, c = self._chips.body_ids[chip], self._session.client
        pybullet.changeDynamics(body, -1, mass=0.0, physicsClientId=c)
        pybullet.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        pybullet.changeDynamics(
            body, -1, activationState=pybullet.ACTIVATION_STATE_SLEEP, physicsClientId=c
        )
        self._set_group(body, moving=False)

    def wake(self, chip: int) -> None:
        """Give a frozen chip back its mass (at rest)."""
        body, c = self._chips.body_ids[chip], self._session.client
        pybullet.changeDynamics(
            body,
            -1,
            mass=self._chips.masses[chip],
            localInertiaDiagonal=self._chips.inertia(chip),
            # Awake and never put to sleep by Bullet (after 2 s at rest it would stop
            # updating contacts); freezing is ours to decide.
            activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=c,
        )
        self._set_group(body, moving=True)

    def _set_group(self, body: int, moving: bool) -> None:
        if self._isolated:
            group, mask = (_MOVING, _FLOOR) if moving else (_FROZEN, 0)
        else:
            group, mask = (_MOVING, _MOVING | _FROZEN | _FLOOR) if moving else (_FROZEN, _MOVING)
        pybullet.setCollisionFilterGroupMask(
            body, -1, group, mask, physicsClientId=self._session.client
        )

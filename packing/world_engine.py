"""The PyBullet connection of a :class:`packing.world.ChipWorld`, and the engine's units.

PyBullet behaves best when bodies are about one unit across, so the engine runs in an
internal world of ``MM_PER_UNIT`` millimetres per length unit, grams and seconds. Only
the parts of :mod:`packing.world` (the ``packing/world_*.py`` modules) use this scale;
everything outside them is in millimetres.
"""

from __future__ import annotations

from chipstack.packing.bullet import pybullet

__all__ = ["MM_PER_UNIT", "GRAVITY_MM_S2", "RESTITUTION_THRESHOLD_MM_S", "EngineSession"]

MM_PER_UNIT = 10.0  # the one place where the internal length scale lives
GRAVITY_MM_S2 = 9810.0
_CONTACT_ERP = 0.5
# Impacts slower than this do not bounce (PyBullet: 0.2 units/s = 2 mm/s here). Without it the
# paper preset's restitution of 1 keeps chips resting on soft contacts vibrating for ever.
RESTITUTION_THRESHOLD_MM_S = 20.0


class EngineSession:
    """One PyBullet physics client, from :meth:`connect` to :meth:`disconnect`.

    The parts of a world hold the session rather than the client id, so that any use
    outside the world's ``with`` block fails with a clear error.
    """

    def __init__(self) -> None:
        self._client: int | None = None

    def connect(self, time_step_s: float, solver_iterations: int) -> int:
        """Connect (no GUI), set gravity and the solver; returns the client id."""
        self._client = pybullet.connect(pybullet.DIRECT)
        c = self._client
        pybullet.setGravity(0, 0, -GRAVITY_MM_S2 / MM_PER_UNIT, physicsClientId=c)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=time_step_s,
            numSolverIterations=solver_iterations,
            deterministicOverlappingPairs=1,
            contactERP=_CONTACT_ERP,
            restitutionVelocityThreshold=RESTITUTION_THRESHOLD_MM_S / MM_PER_UNIT,
            physicsClientId=c,
        )
        return c

    def disconnect(self) -> None:
        if self._client is not None:
            pybullet.disconnect(physicsClientId=self._client)
            self._client = None

    @property
    def client(self) -> int:
        if self._client is None:
            raise RuntimeError("ChipWorld used outside its `with` block")
        return self._client

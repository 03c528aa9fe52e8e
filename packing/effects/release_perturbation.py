"""A spin given to the chip as its holder lets go."""

from __future__ import annotations

import numpy as np

from chipstack.packing.effects.base import Effect


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


RELEASE_PERTURBATION = ReleasePerturbation()

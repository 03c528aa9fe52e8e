"""Packing stage: PyBullet batch deposition of chips into a settled :class:`Stack`."""

import logging

from core.errors import ChipstackError, InputError, SimulationError
from core.schema import Scenario, scenario_from_dict, scenario_to_dict
from packing.deposition import deposit
from packing.presets import PRESETS, PhysicsPreset
from packing.shapes import SHAPES, ChipShape, make_shape
from packing.stack import BatchResult, Stack
from packing.world import GROUND, MM_PER_UNIT, ChipWorld, ContactRecord

__all__ = [
    "BatchResult",
    "ChipShape",
    "ChipWorld",
    "ChipstackError",
    "ContactRecord",
    "GROUND",
    "InputError",
    "MM_PER_UNIT",
    "PRESETS",
    "PhysicsPreset",
    "SHAPES",
    "Scenario",
    "SimulationError",
    "Stack",
    "deposit",
    "make_shape",
    "scenario_from_dict",
    "scenario_to_dict",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())  # the application decides

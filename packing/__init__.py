"""Packing stage: PyBullet batch deposition of chips into a settled :class:`Stack`."""

import logging
from typing import TYPE_CHECKING

from chipstack.core.errors import ChipstackError, InputError, SimulationError
from chipstack.core.lazy import lazy_package
from chipstack.core.scenario_data import scenario_from_dict, scenario_to_dict
from chipstack.core.schema import Scenario
from chipstack.packing.presets import PRESETS, PhysicsPreset

if TYPE_CHECKING:
    from chipstack.core.stack import BatchResult, Stack
    from chipstack.packing.deposition import deposit
    from chipstack.packing.shapes import SHAPES, ChipShape, make_shape
    from chipstack.packing.world import GROUND, MM_PER_UNIT, ChipWorld, ContactRecord

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

# Imported on first use: every command-line start imports packing.stage, hence this
# package, and these modules bring numpy, scipy, trimesh and pybullet (~1 s).
lazy_package(
    __name__,
    {
        "deposit": "chipstack.packing.deposition",
        "SHAPES": "chipstack.packing.shapes",
        "ChipShape": "chipstack.packing.shapes",
        "make_shape": "chipstack.packing.shapes",
        "BatchResult": "chipstack.core.stack",
        "Stack": "chipstack.core.stack",
        "GROUND": "chipstack.packing.world",
        "MM_PER_UNIT": "chipstack.packing.world",
        "ChipWorld": "chipstack.packing.world",
        "ContactRecord": "chipstack.packing.world",
    },
)

logging.getLogger(__name__).addHandler(logging.NullHandler())  # the application decides

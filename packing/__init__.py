"""Packing stage: PyBullet batch deposition of chips into a settled :class:`Stack`."""

import logging
from typing import TYPE_CHECKING

from core.errors import ChipstackError, InputError, SimulationError
from core.lazy import lazy_package
from core.schema import Scenario, scenario_from_dict, scenario_to_dict
from packing.presets import PRESETS, PhysicsPreset

if TYPE_CHECKING:
    from core.stack import BatchResult, Stack
    from packing.deposition import deposit
    from packing.shapes import SHAPES, ChipShape, make_shape
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

# Imported on first use: every command-line start imports packing.stage, hence this
# package, and these modules bring numpy, scipy, trimesh and pybullet (~1 s).
lazy_package(
    __name__,
    {
        "deposit": "packing.deposition",
        "SHAPES": "packing.shapes",
        "ChipShape": "packing.shapes",
        "make_shape": "packing.shapes",
        "BatchResult": "core.stack",
        "Stack": "core.stack",
        "GROUND": "packing.world",
        "MM_PER_UNIT": "packing.world",
        "ChipWorld": "packing.world",
        "ContactRecord": "packing.world",
    },
)

logging.getLogger(__name__).addHandler(logging.NullHandler())  # the application decides

"""The neutral core under every stage: the typed scenario schema, the error types, the
registry mechanism and the stage mechanism. It imports no stage package."""

import logging

from chipstack.core.errors import ChipstackError, InputError, SimulationError, printable
from chipstack.core.registry import Registry
from chipstack.core.scenario_data import scenario_from_dict, scenario_to_dict
from chipstack.core.schema import Scenario
from chipstack.core.stages import Stage, StageInputs, StageOptions, StageOutput, load_stages

__all__ = [
    "ChipstackError",
    "InputError",
    "Registry",
    "Scenario",
    "SimulationError",
    "Stage",
    "StageInputs",
    "StageOptions",
    "StageOutput",
    "load_stages",
    "printable",
    "scenario_from_dict",
    "scenario_to_dict",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())

"""The packing stage: deposit a stack, fill a container, pour a mat or drop single chips,
as the scenario's kind says (:mod:`packing.kinds`), and write ``packing/``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError
from chipstack.core.files import file_sha256
from chipstack.core.provenance import code_versions
from chipstack.core.schema import Scenario, parameter_fields
from chipstack.core.stages import Stage, StageInputs, StageOutput
from chipstack.packing.kinds import SCENARIO_CHOICE, SCENARIO_KINDS, ChipExtent, kind_of_summary
from chipstack.packing.presets import PRESETS
from chipstack.packing.sections import SECTIONS
from chipstack.packing.shape_kinds import SHAPE_CHOICE, check_chip

if TYPE_CHECKING:
    from chipstack.core.stack import Stack

__all__ = ["PackingStage", "STAGE", "check_packing"]


class PackingStage(Stage):
    """Batch deposition (``stack``, ``container``), a mat poured onto a moving belt
    (``conveyor``; later stages take the panel cut from it) or single-chip drops (``drop``)."""

    name = "packing"
    progress_label = "depositing"
    progress_unit = "batch"
    checkpointed = True

    kind_choices = {"chip": SHAPE_CHOICE}  # [chip] and [[mix]]: the shape's own keys
    scenario_choice = SCENARIO_CHOICE  # ``kind``: the scenario kind (scenario.chosen)

    # What the stage runs, declares and reads follows the scenario-kind registry, so that
    # a kind from a plugin runs, and its own table is validated and in the cache key.
    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(SCENARIO_KINDS.in_order())

    @property
    def owned_sections(self) -> tuple[type, ...]:
        own = [t for name in self.kinds for t in SCENARIO_KINDS.get(name).sections]
        return (*SECTIONS, *dict.fromkeys(t for t in own if t not in SECTIONS))

    @property
    def sections(self) -> tuple[str, ...]:
        return ("kind", "seed", "chip", "mix", *(t.table for t in self.owned_sections))

    def check(self, scenario: Scenario) -> None:
        check_packing(scenario)

    def key_extra(self, scenario: Scenario, options) -> dict[str, Any]:
        files = {}
        for spec in scenario.chips:
            for name, path in spec.paths().items():
                try:
                    digest = file_sha256(path)
                except OSError as exc:
                    raise InputError(f"chip.{name} {path!r}: unreadable ({exc.strerror})") from None
                files[path] = digest
        extra: dict[str, Any] = {"files": files, "versions": code_versions()}
        extra.update(scenario.chosen.key_extra(scenario, options))
        return extra

    def compute(self, inputs: StageInputs) -> Any:
        return inputs.scenario.chosen.compute(inputs, self.name)

    def write(self, result: Any, folder: Path, inputs: StageInputs) -> StageOutput:
        return inputs.scenario.chosen.write(result, folder, inputs)

    def handoff(self, result: Any, scenario: Scenario) -> Any:
        return scenario.chosen.handoff(result)

    def load(self, folder: Path, scenario: Scenario) -> Stack | None:
        return scenario.chosen.load(folder, scenario)

    def manifest_entry(self, summary: Mapping[str, Any]) -> dict[str, Any]:
        return dict(summary)  # packing (and container) or drop, at the top level

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        kind = kind_of_summary(summary)
        return kind.report(summary, folder) if kind is not None else []


STAGE = PackingStage()


def check_packing(scenario: Scenario) -> None:
    """The scenario values the packing stage needs: its kind, the preset, chip shapes and
    sizes, and what the kind asks of them (chips that fit its target, container or belt
    and clear the floor at release)."""
    kind = scenario.chosen
    PRESETS.get(scenario.physics.preset, key="physics.preset")
    chips = []
    for index, spec in enumerate(scenario.chips):
        key = f"mix[{index}]" if scenario.mix else "chip"
        across, radius = check_chip(spec, key)
        grow = 1 + spec.size_spread if spec.size_distribution == "uniform" else 1.0
        # The key that sets its size: its length, else its geometry file, else its shape.
        sized = "length_mm" if "length_mm" in parameter_fields(type(spec.params)) else None
        sized = sized or next(iter(spec.paths()), "shape")
        chips.append(ChipExtent(key, across * grow, radius * grow, f"{key}.{sized}"))
        kind.check_chip(scenario, chips[-1])
    kind.check(scenario, chips)

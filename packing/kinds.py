"""Scenario kinds, each one object registered by name: what the packing stage checks,
runs, writes, reads back and reports for a ``stack``, ``container``, ``conveyor`` or
``drop`` scenario.

The packing stage asks the scenario's kind (``scenario.chosen``, resolved once when the
scenario is made) and never tests its name; a package adds a kind through the
``chipstack.scenario_kinds`` entry-point group. A kind's own table (``[drop]``,
``[container]``, ``[conveyor]``) is a :class:`~core.schema.Section` of
:mod:`packing.sections` with that kind in its ``kinds``; where its chips are released and
what holds them is its deposition site (:mod:`packing.sites`, ``kind.site``).

Every command-line start registers the kinds, so they are declared here without the
numerical libraries: each step names the function that does it (``"module:function"``,
imported when a kind first does one of these; a conveyor's check weighs its pour zone
with :mod:`packing.conveyor`'s numerics).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

from chipstack.core.errors import InputError
from chipstack.core.lazy import named
from chipstack.core.registry import Registry
from chipstack.core.schema import KindChoice, Scenario
from chipstack.core.stages import StageInputs, StageOptions, StageOutput
from chipstack.packing.files import write_stack_files
from chipstack.packing.sections import ContainerSpec, ConveyorSpec, DropSpec
from chipstack.packing.site_kinds import SITES

if TYPE_CHECKING:
    from chipstack.core.stack import Stack
    from chipstack.packing.conveyor import ConveyorResult

__all__ = ["SCENARIO_KINDS", "ScenarioKind", "ChipExtent", "kind_of_summary", "stack_kinds"]

log = logging.getLogger(__name__)

STEADY_DRIFT = 0.1  # a steady part whose thickness drifts more than this is flagged


class ChipExtent(NamedTuple):
    """One chip spec's size, grown by its size spread: its key (``chip``, ``mix[i]``),
    how far it reaches across (mm), its circumradius (mm) and the key that sets its size
    (``chip.length_mm``; a file chip's ``chip.file``)."""

    key: str
    across_mm: float
    radius_mm: float
    size_key: str = ""


class ScenarioKind:
    """Base of a scenario kind. Subclasses set the class attributes and override what
    differs.

    name: the value of the scenario's ``kind``.
    makes_stack: its packing leaves a :class:`~core.stack.Stack` (``stack.npz``).
    later_stages: the later stages (geometry, mesh, solve) run on that stack.
    summary_keys: the top-level manifest entries its packing writes (the command line's
    summary of a run is told apart by them).
    sections: its own scenario tables (:class:`~core.schema.Section` classes with this
    kind in their ``kinds``), which the packing stage declares for it.
    """

    name: ClassVar[str] = ""
    makes_stack: ClassVar[bool] = True
    later_stages: ClassVar[bool] = True  # its stack goes on to geometry, mesh and solve
    summary_keys: ClassVar[frozenset[str]] = frozenset({"packing"})
    sections: ClassVar[tuple[type, ...]] = ()  # its own scenario tables (Section classes)

    @property
    def site(self):
        """Where its chips are released and what holds them (:mod:`packing.sites`)."""
        return SITES.get(self.name, key="kind")

    def check_chip(self, scenario: Scenario, chip: ChipExtent) -> None:
        """Refuse a chip this kind cannot take (``InputError``), each as it is checked."""

    def check(self, scenario: Scenario, chips: list[ChipExtent]) -> None:
        """Refuse release settings this kind cannot take for its ``chips``."""

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        """What else the packing's result depends on for this kind."""
        return {}

    def compute(self, inputs: StageInputs, stage_name: str) -> Any:
        raise NotImplementedError

    def write(self, result: Any, folder: Path, inputs: StageInputs) -> StageOutput:
        raise NotImplementedError

    def handoff(self, result: Any) -> Any:
        """What later stages read of a computed result (as :meth:`load` gives it back)."""
        return result

    def load(self, folder: Path, scenario: Scenario) -> Stack | None:
        """The stack back from a written folder (None for a kind that makes none)."""
        if not self.makes_stack:
            return None
        return named("chipstack.packing.checkpoint:load_stack")(folder)

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        """Lines for the command line's summary of a finished packing."""
        return []


SCENARIO_KINDS: Registry[ScenarioKind] = Registry("scenario kind", "chipstack.scenario_kinds")
# How the scenario's ``kind`` chooses its kind (the packing stage declares it).
SCENARIO_CHOICE = KindChoice.of_registry(SCENARIO_KINDS)


def _register(cls: type[ScenarioKind]) -> type[ScenarioKind]:
    SCENARIO_KINDS.register(cls.name, cls())
    return cls


def stack_kinds() -> tuple[str, ...]:
    """The kinds whose stack goes on to the later stages (their ``Stage.kinds``)."""
    return tuple(n for n in SCENARIO_KINDS.in_order() if SCENARIO_KINDS.get(n).later_stages)


def kind_of_summary(summary: Mapping[str, Any]) -> ScenarioKind | None:
    """The kind whose packing wrote ``summary`` (a run's manifest): the one with the most
    of its entries present."""
    fitting = [
        SCENARIO_KINDS.get(name)
        for name in SCENARIO_KINDS.in_order()
        if SCENARIO_KINDS.get(name).summary_keys <= set(summary)
    ]
    return max(fitting, key=lambda kind: len(kind.summary_keys), default=None)


def _largest_radius(chips: list[ChipExtent]) -> float:
    """The largest circumradius of the chip specs (mm)."""
    return max((chip.radius_mm for chip in chips), default=0.0)


def _release_clears_the_floor(scenario: Scenario, chips: list[ChipExtent]) -> None:
    largest_radius = _largest_radius(chips)
    if scenario.deposition.release_height_mm[0] <= largest_radius:
        raise InputError(
            "deposition.release_height_mm: the lowest release height must clear the chip's "
            f"circumradius ({largest_radius:.1f} mm) so no release pose touches the floor"
        )


@_register
class StackKind(ScenarioKind):
    """Batch deposition on a square target: ``deposition.chips`` chips released
    ``deposition.batch_size`` at a time, each batch settled before the next."""

    name = "stack"

    def check_chip(self, scenario: Scenario, chip: ChipExtent) -> None:
        d = scenario.deposition
        if chip.across_mm > d.target_size_mm:
            raise InputError(
                f"{chip.size_key or chip.key}: the chip ({chip.across_mm:.1f} mm across) is larger "
                f"than the target (deposition.target_size_mm = {d.target_size_mm:g} mm)"
            )

    def check(self, scenario: Scenario, chips: list[ChipExtent]) -> None:
        _release_clears_the_floor(scenario, chips)

    def compute(self, inputs: StageInputs, stage_name: str) -> Stack:
        return named("chipstack.packing.deposition:deposit_stack")(inputs, stage_name)

    def write(self, result: Stack, folder: Path, inputs: StageInputs) -> StageOutput:
        write_stack_files(folder, result)
        return StageOutput(
            {"packing": named("chipstack.packing.writers:packing_summary")(result)},
            list(result.warnings),
        )

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        packing = summary["packing"]
        last = packing["batches"][-1]
        return [
            f"{packing['chips']} chips in {len(packing['batches'])} batches, "
            f"top {last['top_mm']:.1f} mm, {packing['outside_target']} outside the target, "
            f"max interpenetration {last['max_chip_penetration_mm']:.3f} mm"
        ]


@_register
class DropKind(ScenarioKind):
    """Single-chip drops (paper 4.2): ``drop.drops`` releases of one chip, each onto an
    empty target; the final poses, their statistics and Fig. 15."""

    name = "drop"
    makes_stack = False
    later_stages = False
    summary_keys = frozenset({"drop"})
    sections = (DropSpec,)

    def check(self, scenario: Scenario, chips: list[ChipExtent]) -> None:
        largest_radius = _largest_radius(chips)
        if scenario.drop.height_mm <= largest_radius:
            raise InputError(
                f"drop.height_mm: must clear the chip's circumradius ({largest_radius:.1f} mm)"
            )

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        return {"figures": options.figures}  # the drop stage draws Fig. 15

    def compute(self, inputs: StageInputs, stage_name: str):
        return named("chipstack.packing.drop:drop_chips")(inputs.scenario)

    def write(self, result, folder: Path, inputs: StageInputs) -> StageOutput:
        figures = inputs.options.figures
        statistics = named("chipstack.packing.writers:write_drop_files")(
            folder, inputs.scenario, result, figures
        )
        return StageOutput({"drop": statistics}, list(result.warnings))

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        return [f"{summary['drop']['settled']} settled drops written to {folder.parent}"]


@_register
class ContainerKind(StackKind):
    """Filling a cylinder (paper 5): batches poured until the container is full (a
    settled chip's centre of mass inside the wall's footprint at or above the rim)."""

    name = "container"
    later_stages = False  # a fill is described by its own summary (volume fraction)
    summary_keys = frozenset({"packing", "container"})
    sections = (ContainerSpec,)

    def check_chip(self, scenario: Scenario, chip: ChipExtent) -> None:
        wide = 2 * scenario.container.radius_mm
        if chip.across_mm > wide:
            raise InputError(
                f"{chip.size_key or chip.key}: the chip ({chip.across_mm:.1f} mm) is longer than "
                f"the container is wide (2 x container.radius_mm = {wide:g} mm)"
            )

    def check(self, scenario: Scenario, chips: list[ChipExtent]) -> None:
        pass  # released above the rim: no floor to clear

    def write(self, result: Stack, folder: Path, inputs: StageInputs) -> StageOutput:
        output = super().write(result, folder, inputs)
        output.summary["container"] = named("chipstack.packing.writers:container_summary")(
            result, inputs.scenario
        )
        return output


@_register
class ConveyorKind(StackKind):
    """A mat poured continuously onto a moving belt; later stages take the square panel
    cut from the middle of its steady part."""

    name = "conveyor"
    summary_keys = frozenset({"packing", "conveyor"})
    sections = (ConveyorSpec,)

    def check_chip(self, scenario: Scenario, chip: ChipExtent) -> None:
        pass  # the panel is cut from the mat: check_conveyor weighs it against the chips

    def check(self, scenario: Scenario, chips: list[ChipExtent]) -> None:
        largest_radius = _largest_radius(chips)
        # The pour zone's numerics only, not the deposition's work.
        named("chipstack.packing.conveyor:check_conveyor")(scenario, 2 * largest_radius)
        _release_clears_the_floor(scenario, chips)

    def compute(self, inputs: StageInputs, stage_name: str) -> ConveyorResult:
        return named("chipstack.packing.conveyor:pour")(inputs, stage_name)

    def write(self, result: ConveyorResult, folder: Path, inputs: StageInputs) -> StageOutput:
        scenario = inputs.scenario
        write_stack_files(folder, result.panel)
        summary = named("chipstack.packing.writers:write_mat_files")(
            folder, scenario, result.mat, inputs.options.figures
        )
        warnings = list(result.warnings)
        drift = (summary["thickness"] or {}).get("drift", 0.0)
        if math.isfinite(drift) and abs(drift) > STEADY_DRIFT:
            message = (
                f"the mat's steady part is not steady: its thickness changed by "
                f"{100 * drift:+.0f} % from its first third to its last; raise "
                "conveyor.run_in_mm (and deposition.chips)"
            )
            log.warning(message)
            warnings.append(message)
        return StageOutput(
            {
                "packing": named("chipstack.packing.writers:packing_summary")(result.panel),
                "conveyor": summary,
            },
            warnings,
        )

    def handoff(self, result: ConveyorResult) -> Stack:
        return result.panel  # later stages take the panel cut from the mat, as load() does

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        packing, mat = summary["packing"], summary["conveyor"]
        last = packing["batches"][-1]
        weight = mat.get("areal_weight") or {}
        return [
            f"{mat['chips']['released']} chips poured onto the belt "
            f"({mat['chips']['on_belt']} on it, {mat['chips']['spilled']} spilled) in "
            f"{mat['time']['wall_s']:.1f} s; mat {mat['mat_length_mm']:.0f} mm long, "
            f"areal weight {weight.get('mean_g_m2', float('nan')):.0f} g/m^2 "
            f"(CV {weight.get('cv', float('nan')):.3f} over "
            f"{weight.get('cell_mm', float('nan')):g} mm cells)",
            f"panel {mat['panel_mm']:g} mm square: {packing['chips']} chips, top "
            f"{last['top_mm']:.1f} mm",
        ]

"""Every descriptor of a stack, by name, as plain JSON-ready sections.

``describe`` runs the registered descriptors on a stack's history (one arrangement per
deposited batch, NBD 1, 2, ...) and returns, per descriptor, its record (arrays for
figures and tables) and its section of ``descriptors.json``: named scalars and profiles,
each with its unit and a one-line definition.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from chipstack.core.arrangement import Arrangement, stack_history
from chipstack.core.errors import InputError
from chipstack.geometry.descriptor_kinds import DESCRIPTORS
from chipstack.geometry.descriptors.base import Context
from chipstack.geometry.sections import GeometrySpec

if TYPE_CHECKING:
    from chipstack.core.stages import StageInputs

__all__ = ["Description", "describe", "describe_stack", "SCHEMA", "check_names", "in_output_order"]

SCHEMA = "chipstack.descriptors/1"


def in_output_order(names) -> list[str]:
    """The registered ones of descriptor ``names``, in the order their columns and their
    parts of the reports come (``Descriptor.order``)."""
    return sorted((n for n in names if n in DESCRIPTORS), key=lambda n: DESCRIPTORS.get(n).order)


# -- running them --------------------------------------------------------------------------
@dataclass(frozen=True)
class Description:
    """Records (arrays) and JSON sections of the descriptors that were computed."""

    records: dict[str, Any]
    sections: dict[str, dict[str, Any]]
    timings_s: dict[str, float]
    spec: GeometrySpec

    def to_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "parameters": {
                f.name: getattr(self.spec, f.name) for f in dataclasses.fields(self.spec)
            },
            "descriptors": self.sections,
        }  # timings go to the run's manifest: a result file holds only results


def check_names(names: Sequence[str] | None) -> list[str]:
    """The descriptors to compute, in registry order; raises naming an unknown one."""
    if names is None:
        return DESCRIPTORS.in_order()
    for name in names:
        DESCRIPTORS.get(name, key="descriptors")
    return [n for n in DESCRIPTORS.in_order() if n in set(names)]


def describe(
    history: Sequence[Arrangement],
    spec: GeometrySpec | None = None,
    names: Sequence[str] | None = None,
) -> Description:
    """Compute the named descriptors (all by default) of a stack's history.

    ``history``: the stack after each batch, in order; the last one is the stack.
    """
    if not history:
        raise InputError("history: no arrangement to describe")
    spec = spec or GeometrySpec()
    selected = check_names(names)
    ctx = Context(history, spec)
    records, sections, timings = {}, {}, {}
    for name in selected:
        start = time.perf_counter()
        records[name], sections[name] = DESCRIPTORS.get(name).compute(ctx)
        timings[name] = time.perf_counter() - start
    return Description(records, sections, timings, spec)


def describe_stack(inputs: StageInputs, stage_name: str) -> Description:
    """The description of the packing's stack after each batch, reported as one step."""
    history = stack_history(inputs.result("packing"))
    report = inputs.options.progress
    if report is not None:
        report(stage_name, 0, 1, {})
    description = describe(history, inputs.scenario.geometry, inputs.options.descriptors)
    if report is not None:
        report(stage_name, 1, 1, {})
    return description

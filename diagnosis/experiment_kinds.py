"""The experiment kinds, registered by name: what an experiment spec's ``kind`` may be.
They are implemented (and registered) by :mod:`diagnosis.spec`, with the diagnosis's
numerics, imported when one is first asked for: listing the names loads no numerical
library."""

from __future__ import annotations

from typing import TYPE_CHECKING

from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.diagnosis.spec import ExperimentKind

__all__ = ["EXPERIMENT_KINDS"]

EXPERIMENT_KINDS: Registry[ExperimentKind] = Registry(
    "experiment kind", "chipstack.experiment_kinds"
)
EXPERIMENT_KINDS.declare("chipstack.diagnosis.spec", "drop", "stack", "container")

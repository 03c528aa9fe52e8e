"""The stage mechanism: what a stage is, and the registry the pipeline loops over.

A stage is one object registered by name in its own package (``packing.stage``,
``geometry.stage``, ``meshing.stage``, ...). It declares what its result depends on
(the scenario tables it reads, the stages upstream of it, anything else through
:meth:`Stage.key_extra`), computes its result as a function of them, writes its folder
and reads it back. ``pipeline/`` knows no stage by name: it orders the registry by the
declared dependencies and gives every stage caching, journalling, resume and locks.

Stages are found through the ``chipstack.stages`` entry-point group (``pyproject.toml``),
so adding one is one module and one line there; nothing here imports a stage package.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from chipstack.core.errors import InputError, printable
from chipstack.core.registry import Registry

if TYPE_CHECKING:
    from chipstack.core.schema import Scenario

__all__ = [
    "Stage",
    "StageOptions",
    "StageInputs",
    "StageOutput",
    "STAGES",
    "load_stages",
    "stage_names",
    "check_stage_name",
    "chain",
]

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "chipstack.stages"


@dataclass(frozen=True)
class StageOptions:
    """Run-wide choices that are not scenario keys (command-line flags)."""

    descriptors: tuple[str, ...] | None = None
    figures: bool = True
    progress: Callable[..., None] | None = None  # stage-specific progress callback


class Checkpoint:
    """Where a long stage saves and finds its partial state (the run directory provides
    it; ``None`` outside a run directory, for ensemble workers)."""

    def resume(self, decode: Callable[[dict, str], Any]) -> Any:  # pragma: no cover
        """``decode(arrays, where)`` of the state a killed run saved, or None to start
        afresh. The decoded state's ``batches_done`` must match the journal's count."""
        raise NotImplementedError

    def save(self, arrays: dict[str, Any], done: int) -> None:  # pragma: no cover
        """Save the state (arrays) after ``done`` completed batches."""
        raise NotImplementedError


@dataclass
class StageInputs:
    """What a stage computes from: the scenario, the options and upstream results.

    ``result(name)`` returns an upstream stage's result, computed in this run or read
    back from its folder (``Stage.load``) when the stage was reused from the cache.
    """

    scenario: Scenario
    options: StageOptions
    results: Callable[[str], Any]
    checkpoint: Checkpoint | None = None

    def result(self, name: str) -> Any:
        return self.results(name)


@dataclass
class StageOutput:
    """What a stage's ``write`` returns: its manifest entry and warnings."""

    summary: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)


class Stage:
    """Base of every stage. Subclasses set the class attributes and override the methods.

    Attributes
    ----------
    name: the stage's name (``--to NAME``, its folder in the run directory).
    upstream: stages whose results this one reads (their results come first).
    sections: the scenario tables (or top-level keys) its cache key depends on.
    owned_sections: the scenario tables it declares (:class:`core.schema.Section`
        classes in its own package); the scenario is assembled from what stages own.
    kind_choices: the tables whose selector key chooses a kind of this stage's, each
        kind with its own keys (:class:`core.schema.KindChoice`).
    kinds: the scenario kinds it applies to (a drop scenario has only the packing stage).
    checkpointed: whether it saves partial state to resume from (the packing's batches).
    in_ensembles: whether ``--repeats`` may run it (meshes are made of single runs).
    repeat_statistics: whether an ensemble ending with it gets statistics over repeats.
    """

    name: ClassVar[str] = ""
    upstream: ClassVar[tuple[str, ...]] = ()
    sections: ClassVar[tuple[str, ...]] = ()
    owned_sections: ClassVar[tuple[type, ...]] = ()
    # Tables whose selector key chooses a kind with its own keys: table name ->
    # core.schema.KindChoice (the packing stage's ``chip`` chooses among the shapes).
    kind_choices: ClassVar[Mapping[str, Any]] = {}
    # A conveyor's packing leaves the panel cut from its mat: a stack like any other.
    kinds: ClassVar[tuple[str, ...]] = ("stack", "conveyor")
    checkpointed: ClassVar[bool] = False
    in_ensembles: ClassVar[bool] = True
    repeat_statistics: ClassVar[bool] = False  # summarize_repeats gives an ensemble summary
    progress_label: ClassVar[str] = ""  # what its progress bar says (default: its name)
    progress_unit: ClassVar[str] = "step"

    def check(self, scenario: Scenario) -> None:
        """Refuse scenario values this stage cannot work with (``InputError``)."""

    def check_run(self, scenario: Scenario) -> None:
        """Refuse, before any work, a run of this stage that cannot succeed (a solver
        that is missing, a model the stage cannot take); only when the stage runs."""

    def check_options(self, options: StageOptions) -> None:
        """Refuse options (flags) this stage cannot work with, before any work."""

    def key_extra(self, scenario: Scenario, options: StageOptions) -> dict[str, Any]:
        """What else the result depends on (file contents, code versions, options)."""
        return {}

    def compute(self, inputs: StageInputs) -> Any:
        """The stage's result, from its inputs only (no files written)."""
        raise NotImplementedError

    def write(self, result: Any, folder: Path, inputs: StageInputs) -> StageOutput:
        """Write ``result`` into ``folder`` (built hidden, renamed into place when done)."""
        raise NotImplementedError

    def handoff(self, result: Any, scenario: Scenario) -> Any:
        """What downstream stages read of a result :meth:`compute` returned for
        ``scenario`` (by default all of it; :meth:`load` gives the same from the written
        folder)."""
        return result

    def load(self, folder: Path, scenario: Scenario) -> Any:
        """The result back from a written folder (for downstream stages of a cached run)."""
        raise NotImplementedError

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        """Lines for the command line's summary of a finished run."""
        return []

    def summarize_repeats(self, folders: Sequence[Path], seeds: Sequence[int]) -> Any:
        """Statistics over an ensemble's repeats of this stage (its written folders), or
        None when the stage has none; :meth:`write_repeats` writes them."""
        return None

    def write_repeats(self, summary: Any, path: Callable[[str], Path]) -> None:
        """Write :meth:`summarize_repeats`'s result (``path(name)`` gives where)."""

    def manifest_entry(self, summary: Mapping[str, Any]) -> dict[str, Any]:
        """How the stage's summary appears at the top level of the run's manifest."""
        return {self.name: dict(summary)}


# The stages are entry points like any plugin (the project's own in its pyproject.toml).
STAGES: Registry[Stage] = Registry("stage", ENTRY_POINT_GROUP)
_loaded: list[Stage] = []


def load_stages() -> list[Stage]:
    """Every registered stage, upstream before downstream (loads the entry points once)."""
    if not _loaded:
        _loaded.extend(_ordered([STAGES.get(n) for n in STAGES.names()]))
        if not _loaded:
            raise RuntimeError(f"no stages registered in the {ENTRY_POINT_GROUP!r} entry points")
    return list(_loaded)


def _ordered(stages: Sequence[Stage]) -> list[Stage]:
    """Stages with every stage after its upstream ones (stable by name otherwise)."""
    by_name = {s.name: s for s in stages}
    done: list[Stage] = []

    def visit(stage: Stage, path: tuple[str, ...]) -> None:
        if stage in done:
            return
        if stage.name in path:
            raise RuntimeError(f"stages depend on each other in a circle: {' -> '.join(path)}")
        for name in stage.upstream:
            if name not in by_name:
                raise RuntimeError(f"stage {stage.name!r} needs unknown stage {name!r}")
            visit(by_name[name], (*path, stage.name))
        done.append(stage)

    for stage in sorted(stages, key=lambda s: (_depth(s, by_name), s.name)):
        visit(stage, ())
    return done


def _depth(stage: Stage, by_name: Mapping[str, Stage]) -> int:
    return 1 + max((_depth(by_name[u], by_name) for u in stage.upstream if u in by_name), default=0)


def stage_names() -> list[str]:
    """The stages' names, upstream first."""
    return [s.name for s in load_stages()]


def check_stage_name(name: str, key: str = "--to") -> Stage:
    """The stage called ``name``, or ``InputError`` listing the valid names."""
    for stage in load_stages():
        if stage.name == name:
            return stage
    raise InputError(
        f"{key} {printable(name)}: unknown stage; valid stages: {', '.join(stage_names())}"
    )


def chain(to: str) -> list[Stage]:
    """The stages a run up to ``to`` runs: ``to`` and everything upstream of it, in order.

    With a linear pipeline that is every stage up to ``to``.
    """
    target = check_stage_name(to)
    stages = load_stages()
    return stages[: stages.index(target) + 1]

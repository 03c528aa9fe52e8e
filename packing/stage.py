"""The packing stage: deposit a stack (or drop single chips), write ``packing/``."""

from __future__ import annotations

import json
import logging
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from core.errors import InputError, brief
from core.files import file_sha256
from core.provenance import code_versions
from core.schema import Scenario
from core.stages import Stage, StageInputs, StageOutput
from packing.presets import PRESETS

# The simulation, its records and writers are imported where used: every command-line
# start registers this stage, and they bring numpy, scipy, trimesh and pybullet (~1 s).
if TYPE_CHECKING:
    from packing.drop import DropResult
    from packing.stack import BatchResult, Stack

__all__ = ["PackingStage", "STAGE", "top_mm"]

log = logging.getLogger(__name__)


class PackingStage(Stage):
    """Batch deposition (``stack``, ``container``) or single-chip drops (``drop``)."""

    name = "packing"
    progress_label = "depositing"
    progress_unit = "batch"
    sections = (
        "kind",
        "seed",
        "chip",
        "mix",
        "deposition",
        "physics",
        "settling",
        "output",
        "drop",
        "container",
    )
    kinds = ("stack", "drop", "container")
    checkpointed = True

    def check(self, scenario: Scenario) -> None:
        check_packing(scenario)

    def key_extra(self, scenario: Scenario, options) -> dict[str, Any]:
        files = {}
        for spec in scenario.chips:
            if spec.file:
                try:
                    digest = file_sha256(spec.file)
                except OSError as exc:
                    raise InputError(
                        f"chip.file {spec.file!r}: unreadable ({exc.strerror})"
                    ) from None
                files[spec.file] = digest
        extra: dict[str, Any] = {"files": files, "versions": code_versions()}
        if scenario.kind == "drop":
            extra["figures"] = options.figures  # the drop stage draws Fig. 15
        return extra

    def compute(self, inputs: StageInputs) -> Stack | DropResult:
        from packing.checkpoint import state_from_arrays, state_to_arrays
        from packing.deposition import deposit
        from packing.drop import drop_chips

        scenario = inputs.scenario
        if scenario.kind == "drop":
            return drop_chips(scenario)
        n_batches = -(-scenario.deposition.chips // scenario.deposition.batch_size)
        report = inputs.options.progress

        def progress(batch: int, result: BatchResult | None) -> None:
            if report is not None:
                detail = {}
                if result is not None:  # containers report only their last batch
                    detail = {"chips": len(result.positions), "sim_s": f"{result.sim_time_s:.2f}"}
                report(self.name, batch, n_batches, detail)

        checkpoint = inputs.checkpoint
        resume = checkpoint.resume(state_from_arrays) if checkpoint is not None else None
        if resume is not None:
            progress(resume.batches_done, resume.results[-1] if resume.results else None)
        on_batch = None
        if checkpoint is not None:

            def on_batch(state) -> None:
                checkpoint.save(state_to_arrays(state), state.batches_done)

        return deposit(scenario, progress=progress, resume=resume, on_batch=on_batch)

    def write(self, result: Stack | DropResult, folder: Path, inputs: StageInputs) -> StageOutput:
        from packing.drop import DropResult

        scenario = inputs.scenario
        if isinstance(result, DropResult):
            statistics = write_drop_files(folder, scenario, result, inputs.options.figures)
            return StageOutput({"drop": statistics}, list(result.warnings))
        write_stack_files(folder, result)
        summary: dict[str, Any] = {"packing": packing_summary(result)}
        if scenario.kind == "container":
            summary["container"] = container_summary(result, scenario)
        return StageOutput(summary, list(result.warnings))

    def load(self, folder: Path, scenario: Scenario) -> Stack | None:
        if scenario.kind == "drop":
            return None
        import numpy as np

        from packing.checkpoint import stack_from_arrays

        path = folder / "stack.npz"
        try:
            with np.load(path, allow_pickle=False) as arrays:
                return stack_from_arrays(dict(arrays), str(path))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise InputError(f"{path}: unreadable stack record ({brief(str(exc))})") from None

    def manifest_entry(self, summary: Mapping[str, Any]) -> dict[str, Any]:
        return dict(summary)  # packing (and container) or drop, at the top level

    def report(self, summary: Mapping[str, Any], folder: Path) -> list[str]:
        if "drop" in summary:
            return [f"{summary['drop']['settled']} settled drops written to {folder.parent}"]
        packing = summary["packing"]
        last = packing["batches"][-1]
        return [
            f"{packing['chips']} chips in {len(packing['batches'])} batches, "
            f"top {last['top_mm']:.1f} mm, {packing['outside_target']} outside the target, "
            f"max interpenetration {last['max_chip_penetration_mm']:.3f} mm"
        ]


STAGE = PackingStage()


def check_packing(scenario: Scenario) -> None:
    """The scenario values the packing stage needs: preset, chip shapes and sizes, and
    chips that fit the target and clear the floor at release."""
    from packing.shapes import check_chip  # numpy: when a scenario is checked, not at start

    PRESETS.get(scenario.physics.preset, key="physics.preset")
    d = scenario.deposition
    largest_radius = 0.0
    for index, spec in enumerate(scenario.chips):
        key = f"mix[{index}]" if scenario.mix else "chip"
        across, radius = check_chip(spec, key)
        grow = 1 + spec.size_spread if spec.size_distribution == "uniform" else 1.0
        largest_radius = max(largest_radius, radius * grow)
        if scenario.kind == "stack" and across * grow > d.target_size_mm:
            raise InputError(
                f"{key}.length_mm: the chip ({across * grow:.1f} mm across) is larger than "
                f"the target (deposition.target_size_mm = {d.target_size_mm:g} mm)"
            )
        if scenario.kind == "container" and across * grow > 2 * scenario.container.radius_mm:
            raise InputError(
                f"{key}.length_mm: the chip ({across * grow:.1f} mm) is longer than the "
                "container is wide (2 x container.radius_mm = "
                f"{2 * scenario.container.radius_mm:g} mm)"
            )
    if scenario.kind == "stack" and d.release_height_mm[0] <= largest_radius:
        raise InputError(
            "deposition.release_height_mm: the lowest release height must clear the chip's "
            f"circumradius ({largest_radius:.1f} mm) so no release pose touches the floor"
        )
    if scenario.kind == "drop" and scenario.drop.height_mm <= largest_radius:
        raise InputError(
            f"drop.height_mm: must clear the chip's circumradius ({largest_radius:.1f} mm)"
        )


def write_stack_files(folder: Path, stack: Stack) -> None:
    """The exact record (``stack.npz``), shapes, poses and contacts after each batch, and
    a VTK time series of the stack."""
    import numpy as np

    from export import (
        stack_polydata,
        write_contacts_csv,
        write_poses_csv,
        write_pvd,
        write_stack_vtp,
    )
    from packing.checkpoint import stack_to_arrays
    from packing.shapes import shape_record

    shapes = {"schema": "chipstack.shapes/1", "shapes": [shape_record(s) for s in stack.shapes]}
    (folder / "shapes.json").write_text(json.dumps(shapes) + "\n")
    # The exact record (float64 poses, contacts) later stages start from.
    np.savez(folder / "stack.npz", **stack_to_arrays(stack))
    series = []
    for result in stack.batches:
        tag = f"batch_{result.batch:02d}"
        write_poses_csv(folder / f"poses_after_{tag}.csv", stack, result)
        write_contacts_csv(folder / f"contacts_after_{tag}.csv", result)
        n = len(result.positions)
        mesh = stack_polydata(
            stack.shapes,
            stack.shape_index[:n],
            result.positions,
            result.quaternions,
            stack.batch[:n],
        )
        write_stack_vtp(folder / f"stack_after_{tag}.vtp", mesh)
        series.append((float(result.batch), f"stack_after_{tag}.vtp"))
    write_pvd(folder / "stack.pvd", series)


def write_drop_files(folder: Path, scenario: Scenario, drops: DropResult, figures: bool) -> dict:
    """Every final pose, the statistics and Fig. 15; returns the statistics."""
    from export.tables import write_drops_csv
    from packing.scatter import drop_statistics

    write_drops_csv(folder / "drops.csv", drops)
    statistics = drop_statistics(drops.positions[:, :2], scenario.drop.yaw_deg)
    statistics["settled"] = int(drops.settled.sum())
    (folder / "drop_statistics.json").write_text(json.dumps(statistics, indent=2) + "\n")
    if figures:
        from export.figures import plot_drops  # matplotlib only when drawing

        (folder / "figures").mkdir(exist_ok=True)
        plot_drops(
            folder / "figures" / "fig15_drops.png",
            drops.positions[:, :2],
            statistics,
            scenario.drop.yaw_deg,
        )
    return statistics


def packing_summary(stack: Stack) -> dict[str, Any]:
    """The packing's manifest entry: per batch, counts, times and penetrations."""
    batches = [
        {
            "batch": r.batch,
            "chips": len(r.positions),
            "settled": r.settled,
            "sim_time_s": round(r.sim_time_s, 4),
            "wall_time_s": round(r.wall_time_s, 3),
            "steps": r.steps,
            "wakes": r.wakes,
            "contact_points": len(r.contacts),
            "outside_target": r.outside_target,
            "max_floor_penetration_mm": round(r.max_floor_penetration_mm, 5),
            "max_chip_penetration_mm": round(r.max_chip_penetration_mm, 5),
            "top_mm": round(top_mm(stack, r), 3),
        }
        for r in stack.batches
    ]
    return {
        "chips": stack.n_chips,
        "batches": batches,
        "outside_target": stack.batches[-1].outside_target,
        "all_settled": all(r.settled for r in stack.batches),
    }


def container_summary(stack: Stack, scenario: Scenario) -> dict[str, Any]:
    """How full the container is (volume fraction by centres of mass)."""
    import numpy as np

    from packing.fill import container_fill

    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    c = scenario.container
    return container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)


def top_mm(stack: Stack, result: BatchResult) -> float:
    """Height of the highest point of any chip after ``result``'s batch (mm)."""
    from packing.overlap import vertex_heights_mm

    n = len(result.positions)
    top = 0.0
    for k, shape in enumerate(stack.shapes):
        mine = stack.shape_index[:n] == k
        if mine.any():
            heights = vertex_heights_mm(
                result.positions[mine], result.quaternions[mine], shape.vertices
            )
            top = max(top, float(heights.max()))
    return top

"""``pipeline describe``: the geometry stage on an existing packing run."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError, printable
from chipstack.geometry.describe import check_names, describe
from chipstack.geometry.files import write_geometry
from chipstack.pipeline.atomic import write_atomically
from chipstack.pipeline.rundir import StageWriter
from chipstack.pipeline.stackfiles import load_run

__all__ = ["describe_run"]


def describe_run(
    run_dir: str | Path,
    descriptors: Sequence[str] | None = None,
    figures: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """The geometry stage on an existing packing run: adds ``geometry/`` to it.

    Returns the updated manifest. Nothing is written unless the stage completes.
    """
    check_names(descriptors)
    scenario, history, manifest = load_run(run_dir)
    if "geometry" in manifest.get("stages_completed", []) and not overwrite:
        raise InputError(
            f"{printable(run_dir)}: already described (use --overwrite to describe it again)"
        )
    start = time.perf_counter()
    with StageWriter(run_dir, "geometry") as folder:
        description = describe(history, scenario.geometry, descriptors)
        summary = write_geometry(folder, description, history, scenario, figures)
        manifest["geometry"] = summary
        manifest["stages_completed"] = [
            s for s in manifest.get("stages_completed", []) if s != "geometry"
        ] + ["geometry"]
        manifest.setdefault("wall_time_s", {})["geometry"] = round(time.perf_counter() - start, 3)
    write_atomically(Path(run_dir) / "manifest.json", json.dumps(manifest, indent=2) + "\n")
    return manifest

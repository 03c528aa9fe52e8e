"""``pipeline run``: one run through the stages, or an ensemble of them (``--repeats``),
with a progress bar per stage and each completed stage's summary."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from tqdm import tqdm

from chipstack.core.errors import ChipstackError, InputError
from chipstack.core.stages import check_stage_name, load_stages, stage_names
from chipstack.meshing.stage import check_formats
from chipstack.pipeline.commands import descriptor_names, resumable_interrupt
from chipstack.pipeline.ensemble import run_ensemble
from chipstack.pipeline.run import run_pipeline
from chipstack.pipeline.scenario_files import load_scenario, parse_setting

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    # A key set twice takes its last value, as a later line of a file would.
    settings = dict(parse_setting(text) for text in args.set)
    scenario = load_scenario(args.scenario, settings)
    if args.seed is not None:
        scenario = scenario.with_seed(args.seed)
    out = args.out or f"runs/{scenario.name}-seed{scenario.seed}"
    descriptors = descriptor_names(args.descriptors)
    if descriptors is not None and args.to in (None, stage_names()[0]):
        raise ChipstackError("--descriptors: only with --to geometry or a later stage")
    if args.formats is not None:
        formats = tuple(f.strip() for f in args.formats.split(",") if f.strip())
        check_formats(formats, "--formats")
        if "mesh" not in {t.table for t in scenario.tables}:
            raise InputError(f"--formats: a {scenario.kind} scenario is not meshed")
        scenario = dataclasses.replace(
            scenario, mesh=dataclasses.replace(scenario.mesh, formats=formats)
        )
    if args.repeats is not None:
        _ensemble(args, scenario, out, descriptors, settings)
        return
    if args.workers is not None or args.scheduler is not None:
        raise ChipstackError("--workers, --scheduler: only with --repeats (a single run is local)")
    bars = _StageBars(args.quiet)
    try:
        path, _, manifest = run_pipeline(
            scenario,
            out,
            to=args.to,
            overwrite=args.overwrite,
            progress=bars.update,
            command=sys.argv,
            descriptors=descriptors,
            settings=settings,
        )
    finally:
        bars.close()
    if not args.quiet:
        _print_run(path, manifest)


class _StageBars:
    """One progress bar per stage, drawn at its first report (so that early errors
    stay one line) and closed when the next stage starts."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar = None
        self.stage = None

    def update(self, stage: str, done: int, total: int, detail: dict) -> None:
        if stage != self.stage:
            self.close()
            self.stage = stage
            registered = check_stage_name(stage)
            self.bar = tqdm(
                total=total,
                desc=registered.progress_label or stage,
                unit=registered.progress_unit,
                disable=self.quiet,
                file=sys.stderr,
            )
        if detail:
            self.bar.set_postfix(detail)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _print_run(path, manifest: dict) -> None:
    """Each completed stage's lines of summary, with where the run was written."""
    times = manifest["wall_time_s"]
    if manifest["stages_reused"]:
        print(f"reused (inputs unchanged): {', '.join(manifest['stages_reused'])}")
    first = load_stages()[0]
    for stage in load_stages():
        if stage.name not in manifest["stages_completed"]:
            continue
        summary = manifest if stage is first else manifest.get(stage.name, {})
        lines = stage.report(summary, Path(path) / stage.name)
        if stage is first and lines and "drop" not in manifest:
            took = f"{times[stage.name]:.1f} s" if stage.name in times else "reused"
            lines[0] += f"; deposition {took}; written to {path}"
        for line in lines:
            print(line)


def _ensemble(args: argparse.Namespace, scenario, out: str, descriptors, settings) -> None:
    bars: list[tqdm] = []

    def progress(finished: int, total: int) -> None:
        """``finished`` more runs are done (the first call: those resumed from disk)."""
        if not bars:
            bars.append(
                tqdm(total=total, desc="repeats", unit="run", disable=args.quiet, file=sys.stderr)
            )
        bars[0].update(finished)

    try:
        path, manifest = run_ensemble(
            scenario,
            out,
            args.repeats,
            to=args.to,
            overwrite=args.overwrite,
            progress=progress,
            command=sys.argv,
            descriptors=descriptors,
            workers=args.workers,
            scheduler=args.scheduler,
            settings=settings,
        )
    except KeyboardInterrupt:
        for bar in bars:
            bar.close()
        resumable_interrupt("runs", out)
    finally:
        for bar in bars:
            bar.close()
    if not args.quiet:
        _print_ensemble(path, manifest, args.repeats)


def _print_ensemble(path, manifest: dict, repeats: int) -> None:
    resumed = len(manifest["resumed_runs"])
    if resumed:
        print(f"resumed: {resumed} runs were already written")
    failed = len(manifest["failed_runs"])
    if failed:
        print(f"{failed} of {repeats} runs failed (see the warnings and the manifest)")
    seconds = manifest["wall_time_s"]["total"]
    print(f"{repeats - failed} of {repeats} repeats in {seconds:.1f} s; written to {path}")
    if "geometry" in manifest["stages_completed"]:
        summary = json.loads((Path(path) / "ensemble.json").read_text())
        d = summary["descriptors"]
        # Here, not at the top: the descriptors' module brings numpy, scipy and manifold3d,
        # which every run (and its one-line errors) would otherwise wait for at its start.
        from chipstack.geometry.describe import in_output_order
        from chipstack.geometry.descriptor_kinds import DESCRIPTORS

        shown = in_output_order(d)
        for section in shown:
            for key in DESCRIPTORS.get(section).ensemble_scalars:
                s = d[section]["scalars"][key]
                print(
                    f"  {section}.{key}: {s['mean']:.4g} "
                    f"(95 % CI {s['ci_low']:.4g} to {s['ci_high']:.4g}) {s['unit']}"
                )

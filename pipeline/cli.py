"""Command line: ``pipeline run``, ``sweep``, ``describe``, ``compare``, ``validate``,
``diagnose`` and ``synth``.

The only place that prints or exits. Every expected failure (bad input, a physics error)
becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from chipstack.core.errors import ChipstackError, InputError, printable
from chipstack.core.schema import MAX_DROPS, MAX_REPEATS, MAX_SEED, MAX_WORKERS
from chipstack.core.stages import check_stage_name, stage_names

__all__ = ["main"]

EXIT_BAD_INPUT = 2
SEED_HELP = "seed of every random draw, 0 to 2**63 - 1"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, no usage block
        sys.stderr.write(f"pipeline: error: {message}\n")
        raise SystemExit(EXIT_BAD_INPUT)


def _bounded(low: float, high: float, kind: type = int):
    """An argparse type: a number of ``kind`` within [low, high] (bounds stated in the
    flag's help; a value outside is one line and exit 2)."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{printable(text)!r} is not a number") from None
        if not low <= value <= high:  # also refuses NaN
            shown = (lambda v: f"{v:g}") if kind is float else str
            raise argparse.ArgumentTypeError(
                f"must be between {shown(low)} and {shown(high)}, got {shown(value)}"
            )
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


WORKERS = _bounded(1, MAX_WORKERS)
SEED = _bounded(0, MAX_SEED)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="pipeline", description="Chip-stack pipeline for composites recycling")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for add in (
        _add_run,
        _add_sweep,
        _add_describe,
        _add_compare,
        _add_validate,
        _add_diagnose,
        _add_synth,
    ):
        add(commands)
    return parser


def _add_run(commands) -> None:
    run = commands.add_parser("run", help="deposit a stack (and later describe and mesh it)")
    run.add_argument(
        "scenario",
        nargs="?",
        default=None,
        help="scenario TOML file or built-in name (default: paper-squares)",
    )
    run.add_argument(
        "--to",
        default=None,
        help=f"last stage: {', '.join(stage_names())} (default: {stage_names()[0]})",
    )
    run.add_argument("--out", default=None, help="run directory (default: runs/<name>-seed<N>)")
    run.add_argument("--seed", type=SEED, default=None, help=SEED_HELP)
    run.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    run.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    run.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    run.add_argument(
        "--repeats",
        type=_bounded(2, MAX_REPEATS),
        default=None,
        help=f"an ensemble of N independent runs, 2 to {MAX_REPEATS} (seeds derived from "
        "--seed), with statistics",
    )
    run.add_argument(
        "--descriptors",
        default=None,
        help="comma-separated descriptors for the geometry stage (default: all)",
    )
    run.add_argument(
        "--workers",
        type=WORKERS,
        default=None,
        help=f"local Dask workers, 1 to {MAX_WORKERS} (default: one per core)",
    )
    run.add_argument(
        "--scheduler", default=None, help="address of a running Dask scheduler to use instead"
    )
    run.add_argument(
        "--formats",
        default=None,
        help="comma-separated mesh files to write with --to mesh (see docs/meshing.md)",
    )


def _add_describe(commands) -> None:
    describe = commands.add_parser("describe", help="the geometry stage on an existing run")
    describe.add_argument("run_dir", help="run directory holding a packing result")
    describe.add_argument("--descriptors", default=None, help="comma-separated (default: all)")
    describe.add_argument("--overwrite", action="store_true", help="describe it again")
    describe.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    describe.add_argument("--quiet", action="store_true", help="no summary")
    describe.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_compare(commands) -> None:
    compare = commands.add_parser(
        "compare", help="do two ensembles differ, descriptor by descriptor"
    )
    compare.add_argument("run_a", help="ensemble directory (pipeline run --repeats N)")
    compare.add_argument("run_b", help="ensemble directory")
    compare.add_argument("--out", default=None, help="where to write (default: runs/compare-A-B)")
    compare.add_argument("--overwrite", action="store_true", help="replace an earlier comparison")
    compare.add_argument("--quiet", action="store_true", help="no table on stdout")
    compare.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_dask_flags(parser) -> None:
    """--workers and --scheduler: where the runs go (the execution layer, Dask)."""
    parser.add_argument(
        "--workers", type=WORKERS, default=None, help=f"local Dask workers, 1 to {MAX_WORKERS}"
    )
    parser.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")


def _add_sweep(commands) -> None:
    sweep = commands.add_parser(
        "sweep", help="an ensemble at every point of a grid of scenario values, and a table"
    )
    sweep.add_argument("scenario", help="scenario file or built-in name")
    sweep.add_argument(
        "--vary",
        action="append",
        required=True,
        metavar="KEY=V1,V2,...",
        help="a scenario key and its values (repeat for a grid), e.g. "
        "conveyor.belt_speed_mm_s=10,20,40",
    )
    sweep.add_argument(
        "--repeats",
        type=_bounded(2, MAX_REPEATS),
        required=True,
        help=f"runs per point, 2 to {MAX_REPEATS}",
    )
    sweep.add_argument(
        "--to",
        default="geometry",
        help=f"last stage of each run: {', '.join(stage_names())} (default: geometry)",
    )
    sweep.add_argument("--out", default=None, help="where to write (default: runs/sweep-<name>)")
    sweep.add_argument("--seed", type=SEED, default=None, help=SEED_HELP)
    _add_dask_flags(sweep)
    sweep.add_argument("--overwrite", action="store_true", help="replace earlier points")
    sweep.add_argument("--quiet", action="store_true", help="no progress bar or table")
    sweep.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_validate(commands) -> None:
    validate = commands.add_parser(
        "validate", help="rerun the paper's validation cases and print ours beside the paper's"
    )
    validate.add_argument("--out", default="runs/validation", help="where to write")
    validate.add_argument(
        "--cases", default=None, help="comma-separated: drop, mat, container, mixed (default: all)"
    )
    validate.add_argument(
        "--repeats",
        type=_bounded(2, MAX_REPEATS),
        default=10,
        help=f"repeats per case, 2 to {MAX_REPEATS} (paper: 10)",
    )
    validate.add_argument(
        "--drops",
        type=_bounded(2, MAX_DROPS),
        default=50,
        help=f"drops per experiment, 2 to {MAX_DROPS}",
    )
    validate.add_argument("--seed", type=SEED, default=0, help=SEED_HELP)
    validate.add_argument(
        "--overwrite", action="store_true", help="replace an earlier validation in --out"
    )
    _add_dask_flags(validate)
    validate.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_diagnose(commands) -> None:
    diagnose = commands.add_parser(
        "diagnose", help="where a simulation departs from experiments, and which effect causes it"
    )
    diagnose.add_argument("spec", help="experiment spec (TOML; see the README)")
    diagnose.add_argument(
        "--out", default=None, help="where to write (default: runs/diagnose-<spec>)"
    )
    diagnose.add_argument("--seed", type=SEED, default=0, help=SEED_HELP)
    _add_dask_flags(diagnose)
    diagnose.add_argument(
        "--tables",
        default=None,
        help="where the reference tables of simulated datasets are kept and reused "
        "(default: $XDG_CACHE_HOME/chipstack/tables or ~/.cache/chipstack/tables)",
    )
    diagnose.add_argument("--overwrite", action="store_true", help="replace an earlier diagnosis")
    diagnose.add_argument("--quiet", action="store_true", help="no verdict on stdout")
    diagnose.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_synth(commands) -> None:
    synth = commands.add_parser(
        "synth", help="pseudo-experimental observations from the simulation with chosen effects"
    )
    synth.add_argument("spec", help="experiment spec (TOML): the conditions to simulate")
    synth.add_argument(
        "--effect", action="append", default=[], help="NAME=STRENGTH (repeat for several)"
    )
    synth.add_argument("--seed", type=SEED, default=0, help=SEED_HELP)
    synth.add_argument("-o", "--output", required=True, help="observations CSV to write")
    synth.add_argument(
        "--drops",
        type=_bounded(1, MAX_DROPS),
        default=50,
        help=f"drops per condition (kind drop), 1 to {MAX_DROPS}",
    )
    synth.add_argument(
        "--measurements",
        type=_bounded(2, 1000),
        default=None,
        help="measured depositions per condition (kinds stack and container), 2 to 1000 "
        "(default: the condition's repeats, at least 2)",
    )
    synth.add_argument(
        "--position-sd-mm",
        type=_bounded(0.0, 100.0, float),
        default=None,
        help="measurement noise of positions, 0 to 100 mm (default: the spec's [measurement])",
    )
    synth.add_argument(
        "--angle-sd-deg",
        type=_bounded(0.0, 45.0, float),
        default=None,
        help="measurement noise of yaw and tilt, 0 to 45 deg (default: the spec's [measurement])",
    )
    synth.add_argument(
        "--workers", type=WORKERS, default=None, help=f"local Dask workers, 1 to {MAX_WORKERS}"
    )
    synth.add_argument("--overwrite", action="store_true", help="replace an existing file")
    synth.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _names(text: str | None) -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ChipstackError("--descriptors: give at least one descriptor name")
    return names


def _run(args: argparse.Namespace) -> None:
    from chipstack.pipeline.run import run_pipeline
    from chipstack.pipeline.scenario_files import load_scenario

    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        scenario = scenario.with_seed(args.seed)
    out = args.out or f"runs/{scenario.name}-seed{scenario.seed}"
    descriptors = _names(args.descriptors)
    if descriptors is not None and args.to in (None, stage_names()[0]):
        raise ChipstackError("--descriptors: only with --to geometry or a later stage")
    if args.formats is not None:
        import dataclasses

        from chipstack.meshing.stage import check_formats

        formats = tuple(f.strip() for f in args.formats.split(",") if f.strip())
        check_formats(formats, "--formats")
        if "mesh" not in {t.table for t in scenario.tables}:
            raise InputError(f"--formats: a {scenario.kind} scenario is not meshed")
        scenario = dataclasses.replace(
            scenario, mesh=dataclasses.replace(scenario.mesh, formats=formats)
        )
    if args.repeats is not None:
        _ensemble(args, scenario, out, descriptors)
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
        from tqdm import tqdm

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
    from pathlib import Path

    from chipstack.core.stages import load_stages

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


def _ensemble(args: argparse.Namespace, scenario, out: str, descriptors) -> None:
    from tqdm import tqdm

    from chipstack.pipeline.ensemble import run_ensemble

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
        )
    except KeyboardInterrupt:
        for bar in bars:
            bar.close()
        _resumable_interrupt("runs", out)
    finally:
        for bar in bars:
            bar.close()
    if not args.quiet:
        _print_ensemble(path, manifest, args.repeats)


def _resumable_interrupt(what: str, out) -> None:
    """Ctrl-C in a resumable command: say what is kept, exit 130."""
    sys.stderr.write(
        f"pipeline: interrupted; the {what} already written are kept in {out}: "
        "run the same command to resume\n"
    )
    raise SystemExit(130) from None


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
        import json
        from pathlib import Path

        summary = json.loads((Path(path) / "ensemble.json").read_text())
        d = summary["descriptors"]
        from chipstack.geometry.describe import DESCRIPTORS, in_output_order

        shown = in_output_order(d)
        for section in shown:
            for key in DESCRIPTORS.get(section).ensemble_scalars:
                s = d[section]["scalars"][key]
                print(
                    f"  {section}.{key}: {s['mean']:.4g} "
                    f"(95 % CI {s['ci_low']:.4g} to {s['ci_high']:.4g}) {s['unit']}"
                )


def _describe(args: argparse.Namespace) -> None:
    from chipstack.pipeline.describe import describe_run

    manifest = describe_run(
        args.run_dir,
        _names(args.descriptors),
        figures=not args.no_figures,
        overwrite=args.overwrite,
    )
    if not args.quiet:
        from pathlib import Path

        from chipstack.geometry.stage import STAGE

        folder = Path(args.run_dir) / "geometry"
        for line in STAGE.report(manifest["geometry"], folder):
            print(line)
        print(f"written to {args.run_dir}/geometry ({len(manifest['geometry']['files'])} files)")


def _compare(args: argparse.Namespace) -> None:
    from pathlib import Path

    from chipstack.pipeline.compare import compare_runs

    out = args.out or f"runs/compare-{Path(args.run_a).name}-{Path(args.run_b).name}"
    _, table = compare_runs(args.run_a, args.run_b, out, overwrite=args.overwrite, command=sys.argv)
    if not args.quiet:
        print(table, end="")
        print(f"written to {out}")


def _validate(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from chipstack.pipeline.validate import CASES, table_markdown, validate

    cases = [c.strip() for c in args.cases.split(",") if c.strip()] if args.cases else CASES
    if not cases:
        raise ChipstackError("--cases: give at least one case")
    bar = None

    def progress(step: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, unit="run", desc="validating")
        bar.update(step)

    try:
        rows = validate(
            args.out,
            cases,
            args.repeats,
            args.drops,
            args.seed,
            args.workers,
            args.scheduler,
            progress,
            overwrite=args.overwrite,
            command=sys.argv,
        )
    finally:
        if bar is not None:
            bar.close()
    print(table_markdown(rows))
    print(f"written to {args.out}")


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"pipeline: {record.levelname.lower()}: {record.getMessage()}"


def _diagnose(args: argparse.Namespace) -> None:
    from pathlib import Path

    from chipstack.pipeline.diagnose import diagnose

    out = args.out or f"runs/diagnose-{Path(args.spec).stem}"

    def progress(message: str) -> None:
        # The reference table's build takes minutes the first time: always shown.
        long_work = message.startswith(("reference table", "model choice"))
        if args.verbose or (long_work and not args.quiet):
            sys.stderr.write(f"pipeline: {message}\n")

    path, result = diagnose(
        args.spec,
        out,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        overwrite=args.overwrite,
        progress=progress,
        command=sys.argv,
        tables=args.tables,
    )
    if not args.quiet:
        print(f"{result['verdict']['kind']}: {result['verdict']['text']}")
        print(f"diagnosis in {result['wall_time_s']:.1f} s; report written to {path}/diagnosis.md")


def _synth(args: argparse.Namespace) -> None:
    from chipstack.pipeline.diagnose import synth

    path, rows = synth(
        args.spec,
        args.effect,
        args.seed,
        args.output,
        drops=args.drops,
        measurements=args.measurements,
        overwrite=args.overwrite,
        workers=args.workers,
        position_sd_mm=args.position_sd_mm,
        angle_sd_deg=args.angle_sd_deg,
    )
    print(f"{rows} observations written to {path}")


def _sweep(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from chipstack.pipeline.scenario_files import load_scenario
    from chipstack.pipeline.sweep import parse_vary, run_sweep, sweep_points

    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        scenario = scenario.with_seed(args.seed)
    vary = parse_vary(args.vary)
    check_stage_name(args.to)
    points = sweep_points(scenario, vary)  # every point checked before anything runs
    out = args.out or f"runs/sweep-{scenario.name}"
    bar = tqdm(
        total=len(points) * args.repeats,
        desc="sweep",
        unit="run",
        disable=args.quiet,
        file=sys.stderr,
    )

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    try:
        path, record = run_sweep(
            scenario,
            vary,
            out,
            args.repeats,
            to=args.to,
            overwrite=args.overwrite,
            progress=progress,
            command=sys.argv,
            workers=args.workers,
            scheduler=args.scheduler,
        )
    except KeyboardInterrupt:
        bar.close()
        _resumable_interrupt("points and runs", out)
    finally:
        bar.close()
    if args.quiet:
        return
    print(f"{len(record['points'])} points x {args.repeats} repeats; written to {path}")
    shown = [
        n
        for n in (
            "conveyor.areal_weight.mean_g_m2",
            "conveyor.areal_weight.cv",
            "conveyor.thickness.mean_mm",
            "conveyor.orientation.order_cos2",
            "stack.mean_height_mm",
            "stack.volume_fraction",
        )
        if any(n in p["scalars"] for p in record["points"])
    ]
    for point in record["points"]:
        cells = []
        for name in shown:
            s = point["scalars"].get(name)
            if s and s["mean"] is not None:
                half = "" if s["ci_high"] is None else f" +- {(s['ci_high'] - s['mean']):.3g}"
                cells.append(f"{name.split('.', 1)[1]} {s['mean']:.4g}{half}")
        print(f"{point['dir']}: " + "; ".join(cells))


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # Warnings (an unsettled batch, ...) reach the user through the library's log records,
    # also with --quiet; -v adds the progress details.
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter())
    verbose = getattr(args, "verbose", False)
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, handlers=[handler], force=True
    )
    # Dask reports lost workers and retried tasks itself; the ensemble reports what matters.
    # Set through its configuration (read when distributed is imported, also by workers).
    if not verbose:
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")
    try:
        if args.command == "run":
            _run(args)
        elif args.command == "sweep":
            _sweep(args)
        elif args.command == "describe":
            _describe(args)
        elif args.command == "compare":
            _compare(args)
        elif args.command == "validate":
            _validate(args)
        elif args.command == "diagnose":
            _diagnose(args)
        elif args.command == "synth":
            _synth(args)
    except ChipstackError as exc:
        sys.stderr.write(f"pipeline: error: {exc}\n")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        sys.stderr.write("pipeline: interrupted; nothing was written\n")
        return 130
    except MemoryError:
        sys.stderr.write(
            "pipeline: error: out of memory; choose a coarser mesh.voxel_mm or geometry.voxel_mm, "
            "or fewer chips (nothing was written)\n"
        )
        return EXIT_BAD_INPUT
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

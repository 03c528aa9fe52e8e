"""Command line: ``pipeline run``, ``scenarios``, ``sweep``, ``describe``, ``compare``,
``validate``, ``diagnose`` and ``synth``.

The parser and ``main``; each command's handler is a module of
:mod:`chipstack.pipeline.commands`. These are the only places that print or exit. Every
expected failure (bad input, a physics error) becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable

from chipstack.core.errors import ChipstackError, printable
from chipstack.core.keys import MAX_DROPS, MAX_REPEATS, MAX_SEED, MAX_WORKERS
from chipstack.core.lazy import named
from chipstack.core.stages import stage_names

__all__ = ["main"]

EXIT_BAD_INPUT = 2
SEED_HELP = "seed of every random draw, 0 to 2**63 - 1"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, no usage block
        sys.stderr.write(f"pipeline: error: {message}\n")
        raise SystemExit(EXIT_BAD_INPUT)


def _bounded(low: float, high: float, kind: type = int, high_text: str | None = None):
    """An argparse type: a number of ``kind`` within [low, high] (bounds stated in the
    flag's help; a value outside is one line and exit 2). ``high_text``: the upper bound
    as the reference (docs/cli.md) states it when it depends on the machine."""

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
    # The range, for the reference generated from this parser (pipeline.cli_docs).
    parse.low, parse.high, parse.high_text = low, high, high_text
    return parse


WORKERS = _bounded(1, MAX_WORKERS, high_text="4 per core")
SEED = _bounded(0, MAX_SEED, high_text="2**63 - 1")

# Each command's handler, named by module and imported when that command runs: the
# handlers import the stages' libraries at their top, which --help and a mistyped flag
# must not wait for.
HANDLERS = {
    "run": "chipstack.pipeline.commands.run:main",
    "scenarios": "chipstack.pipeline.commands.scenarios:main",
    "sweep": "chipstack.pipeline.commands.sweep:main",
    "describe": "chipstack.pipeline.commands.describe:main",
    "compare": "chipstack.pipeline.commands.compare:main",
    "validate": "chipstack.pipeline.commands.validate:main",
    "diagnose": "chipstack.pipeline.commands.diagnose:main",
    "synth": "chipstack.pipeline.commands.synth:main",
}


def _handler(command: str) -> Callable[[argparse.Namespace], None]:
    return named(HANDLERS[command])


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="pipeline", description="Chip-stack pipeline for composites recycling")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for add in (
        _add_run,
        _add_scenarios,
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
    run = commands.add_parser(
        "run", help="deposit a stack and take it through the stages up to --to"
    )
    run.add_argument(
        "scenario",
        nargs="?",
        metavar="SCENARIO",
        default=None,
        help="scenario TOML file or built-in name (default: paper-squares)",
    )
    run.add_argument(
        "--to",
        default=None,
        metavar="STAGE",
        help=f"last stage: {', '.join(stage_names())} (default: {stage_names()[0]})",
    )
    run.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one scenario key (repeat for several), the value read as TOML, else as "
        'text: deposition.chips=24, mesh.kind=conformal, \'mesh.formats=["vtu","msh"]\'; '
        "keys of a kind it switches from are dropped (docs/scenarios.md)",
    )
    run.add_argument(
        "--out", metavar="DIR", default=None, help="run directory (default: runs/<name>-seed<N>)"
    )
    run.add_argument("--seed", type=SEED, metavar="N", default=None, help=SEED_HELP)
    run.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    run.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    run.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    run.add_argument(
        "--repeats",
        metavar="N",
        type=_bounded(2, MAX_REPEATS),
        default=None,
        help=f"an ensemble of N independent runs, 2 to {MAX_REPEATS} (seeds derived from "
        "--seed), with statistics",
    )
    run.add_argument(
        "--descriptors",
        metavar="NAMES",
        default=None,
        help="comma-separated descriptors for the geometry stage (default: all)",
    )
    run.add_argument(
        "--workers",
        metavar="N",
        type=WORKERS,
        default=None,
        help=f"local Dask workers, 1 to {MAX_WORKERS} (default: one per core)",
    )
    run.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="address of a running Dask scheduler to use instead",
    )
    run.add_argument(
        "--formats",
        metavar="NAMES",
        default=None,
        help="comma-separated mesh files to write with --to mesh (see docs/meshing.md)",
    )


def _add_scenarios(commands) -> None:
    commands.add_parser(
        "scenarios", help="list the built-in scenarios: name, kind and what each is"
    )


def _add_describe(commands) -> None:
    describe = commands.add_parser("describe", help="the geometry stage on an existing run")
    describe.add_argument(
        "run_dir", metavar="RUN_DIR", help="run directory holding a packing result"
    )
    describe.add_argument(
        "--descriptors", metavar="NAMES", default=None, help="comma-separated (default: all)"
    )
    describe.add_argument("--overwrite", action="store_true", help="describe it again")
    describe.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    describe.add_argument("--quiet", action="store_true", help="no summary")
    describe.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_compare(commands) -> None:
    compare = commands.add_parser(
        "compare", help="do two ensembles differ, descriptor by descriptor"
    )
    compare.add_argument(
        "run_a", metavar="ENSEMBLE_A", help="ensemble directory (pipeline run --repeats N)"
    )
    compare.add_argument("run_b", metavar="ENSEMBLE_B", help="ensemble directory")
    compare.add_argument(
        "--out", metavar="DIR", default=None, help="where to write (default: runs/compare-A-B)"
    )
    compare.add_argument("--overwrite", action="store_true", help="replace an earlier comparison")
    compare.add_argument("--quiet", action="store_true", help="no table on stdout")
    compare.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_dask_flags(parser) -> None:
    """--workers and --scheduler: where the runs go (the execution layer, Dask)."""
    parser.add_argument(
        "--workers",
        metavar="N",
        type=WORKERS,
        default=None,
        help=f"local Dask workers, 1 to {MAX_WORKERS}",
    )
    parser.add_argument(
        "--scheduler", metavar="ADDRESS", default=None, help="address of a running Dask scheduler"
    )


def _add_sweep(commands) -> None:
    sweep = commands.add_parser(
        "sweep", help="an ensemble at every point of a grid of scenario values, and a table"
    )
    sweep.add_argument("scenario", metavar="SCENARIO", help="scenario file or built-in name")
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
        metavar="N",
        type=_bounded(2, MAX_REPEATS),
        required=True,
        help=f"runs per point, 2 to {MAX_REPEATS}",
    )
    sweep.add_argument(
        "--to",
        default="geometry",
        metavar="STAGE",
        help=f"last stage of each run: {', '.join(stage_names())} (default: geometry)",
    )
    sweep.add_argument(
        "--out", metavar="DIR", default=None, help="where to write (default: runs/sweep-<name>)"
    )
    sweep.add_argument("--seed", type=SEED, metavar="N", default=None, help=SEED_HELP)
    _add_dask_flags(sweep)
    sweep.add_argument("--overwrite", action="store_true", help="replace earlier points")
    sweep.add_argument("--quiet", action="store_true", help="no progress bar or table")
    sweep.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_validate(commands) -> None:
    validate = commands.add_parser(
        "validate", help="rerun the paper's validation cases and print ours beside the paper's"
    )
    validate.add_argument("--out", metavar="DIR", default="runs/validation", help="where to write")
    validate.add_argument(
        "--cases",
        metavar="NAMES",
        default=None,
        help="comma-separated: drop, mat, container, mixed (default: all)",
    )
    validate.add_argument(
        "--repeats",
        metavar="N",
        type=_bounded(2, MAX_REPEATS),
        default=10,
        help=f"repeats per case, 2 to {MAX_REPEATS} (paper: 10)",
    )
    validate.add_argument(
        "--drops",
        metavar="N",
        type=_bounded(2, MAX_DROPS),
        default=50,
        help=f"drops per experiment, 2 to {MAX_DROPS}",
    )
    validate.add_argument("--seed", type=SEED, metavar="N", default=0, help=SEED_HELP)
    validate.add_argument(
        "--overwrite", action="store_true", help="replace an earlier validation in --out"
    )
    _add_dask_flags(validate)
    validate.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def _add_diagnose(commands) -> None:
    diagnose = commands.add_parser(
        "diagnose", help="where a simulation departs from experiments, and which effect causes it"
    )
    diagnose.add_argument("spec", metavar="SPEC", help="experiment spec (TOML; see the README)")
    diagnose.add_argument(
        "--out", metavar="DIR", default=None, help="where to write (default: runs/diagnose-<spec>)"
    )
    diagnose.add_argument("--seed", type=SEED, metavar="N", default=0, help=SEED_HELP)
    _add_dask_flags(diagnose)
    diagnose.add_argument(
        "--tables",
        metavar="DIR",
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
    synth.add_argument(
        "spec", metavar="SPEC", help="experiment spec (TOML): the conditions to simulate"
    )
    synth.add_argument(
        "--effect",
        metavar="NAME=STRENGTH",
        action="append",
        default=[],
        help="NAME=STRENGTH (repeat for several)",
    )
    synth.add_argument("--seed", type=SEED, metavar="N", default=0, help=SEED_HELP)
    synth.add_argument(
        "-o", "--output", metavar="FILE", required=True, help="observations CSV to write"
    )
    synth.add_argument(
        "--drops",
        metavar="N",
        type=_bounded(1, MAX_DROPS),
        default=50,
        help=f"drops per condition (kind drop), 1 to {MAX_DROPS}",
    )
    synth.add_argument(
        "--measurements",
        metavar="N",
        type=_bounded(2, 1000),
        default=None,
        help="measured depositions per condition (kinds stack and container), 2 to 1000 "
        "(default: the condition's repeats, at least 2)",
    )
    synth.add_argument(
        "--position-sd-mm",
        metavar="MM",
        type=_bounded(0.0, 100.0, float),
        default=None,
        help="measurement noise of positions, 0 to 100 mm (default: the spec's [measurement])",
    )
    synth.add_argument(
        "--angle-sd-deg",
        metavar="DEG",
        type=_bounded(0.0, 45.0, float),
        default=None,
        help="measurement noise of yaw and tilt, 0 to 45 deg (default: the spec's [measurement])",
    )
    synth.add_argument(
        "--workers",
        metavar="N",
        type=WORKERS,
        default=None,
        help=f"local Dask workers, 1 to {MAX_WORKERS}",
    )
    synth.add_argument("--overwrite", action="store_true", help="replace an existing file")
    synth.add_argument("-v", "--verbose", action="store_true", help="log progress details")


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"pipeline: {record.levelname.lower()}: {record.getMessage()}"


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
        _handler(args.command)(args)
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

"""Command line: ``pipeline run [SCENARIO] --to STAGE --out DIR --seed N [--quiet]``.

The only place that prints or exits. Every expected failure (bad input, a physics error)
becomes one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys

from packing.errors import ChipstackError

__all__ = ["main"]

EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, no usage block
        sys.stderr.write(f"pipeline: error: {message}\n")
        raise SystemExit(EXIT_BAD_INPUT)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="pipeline", description="Chip-stack pipeline for composites recycling")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    run = commands.add_parser("run", help="deposit a stack (and later describe and mesh it)")
    run.add_argument(
        "scenario",
        nargs="?",
        default=None,
        help="scenario TOML file or built-in name (default: paper-squares)",
    )
    run.add_argument("--to", default="packing", help="last stage to run (default: packing)")
    run.add_argument("--out", default=None, help="run directory (default: runs/<name>-seed<N>)")
    run.add_argument("--seed", type=int, default=None, help="seed of every random draw")
    run.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
    run.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    run.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    return parser


def _run(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from pipeline.run import run_pipeline
    from pipeline.scenario_files import load_scenario

    scenario = load_scenario(args.scenario)
    if args.seed is not None:
        if args.seed < 0:
            raise ChipstackError("--seed: must not be negative")
        scenario = scenario.with_seed(args.seed)
    out = args.out or f"runs/{scenario.name}-seed{scenario.seed}"
    n_batches = -(-scenario.deposition.chips // scenario.deposition.batch_size)
    bars: list[tqdm] = []  # drawn at the first batch, so early errors stay one line

    def progress(batch: int, result) -> None:
        if not bars:
            bars.append(
                tqdm(
                    total=n_batches,
                    desc="depositing",
                    unit="batch",
                    disable=args.quiet,
                    file=sys.stderr,
                )
            )
        bars[0].set_postfix(chips=len(result.positions), sim_s=f"{result.sim_time_s:.2f}")
        bars[0].update(1)

    try:
        path, stack, manifest = run_pipeline(
            scenario, out, to=args.to, overwrite=args.overwrite, progress=progress, command=sys.argv
        )
    finally:
        for bar in bars:
            bar.close()
    if not args.quiet:
        summary = manifest["packing"]
        last = summary["batches"][-1]
        print(
            f"{stack.n_chips} chips in {len(stack.batches)} batches, "
            f"top {last['top_mm']:.1f} mm, {summary['outside_target']} outside the target, "
            f"max interpenetration {last['max_chip_penetration_mm']:.3f} mm; "
            f"deposition {manifest['wall_time_s']['packing']:.1f} s; written to {path}"
        )


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
    try:
        if args.command == "run":
            _run(args)
    except ChipstackError as exc:
        sys.stderr.write(f"pipeline: error: {exc}\n")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        sys.stderr.write("pipeline: interrupted; nothing was written\n")
        return 130
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

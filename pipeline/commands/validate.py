"""``pipeline validate``: the paper's validation cases rerun, with a progress bar, and
ours beside the paper's."""

from __future__ import annotations

import argparse
import sys

from tqdm import tqdm

from chipstack.core.errors import ChipstackError
from chipstack.pipeline.validate import CASES, table_markdown, validate

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
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

"""``pipeline describe RUN_DIR``: the geometry stage on an existing run, and its summary."""

from __future__ import annotations

import argparse
from pathlib import Path

from chipstack.geometry.stage import STAGE
from chipstack.pipeline.commands import descriptor_names
from chipstack.pipeline.describe import describe_run

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    manifest = describe_run(
        args.run_dir,
        descriptor_names(args.descriptors),
        figures=not args.no_figures,
        overwrite=args.overwrite,
    )
    if not args.quiet:
        folder = Path(args.run_dir) / "geometry"
        for line in STAGE.report(manifest["geometry"], folder):
            print(line)
        print(f"written to {args.run_dir}/geometry ({len(manifest['geometry']['files'])} files)")

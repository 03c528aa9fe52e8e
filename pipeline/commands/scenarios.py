"""``pipeline scenarios``: the built-in scenarios, one line each (name, kind, what it is)."""

from __future__ import annotations

import argparse

from chipstack.pipeline.scenario_files import builtin_summaries

__all__ = ["main"]


def main(args: argparse.Namespace) -> None:
    rows = builtin_summaries()
    name_width = max(len(name) for name, _, _ in rows)
    kind_width = max(len(kind) for _, kind, _ in rows)
    for name, kind, description in rows:
        print(f"{name:<{name_width}}  {kind:<{kind_width}}  {description}")

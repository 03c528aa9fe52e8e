"""``docs/cli.md``, the command-line reference, generated from the parser itself.

Every command of :mod:`chipstack.pipeline.cli` with its usage, and every argument with
its help, its choices, its range (the bounds its type enforces) and whether it repeats,
read from the ``argparse`` parser that ``pipeline`` runs; the prose that the help strings
have no room for is kept here, by command. ``python -m chipstack.pipeline.cli_docs``
(``make docs``) writes the page, and a test fails when the page is not current, so the
reference cannot drift from the command line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from chipstack.pipeline.cli import _parser

__all__ = ["PAGE", "render", "write_page"]

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "cli.md"
# Usage lines are wrapped at a fixed width, not the terminal's, so that the page is the
# same on every machine.
WIDTH = 88

INTRO = """\
The same runs from Python, results as arrays, DataFrames and meshes: [python](python.md).
Every command refuses bad input (an unknown key, a value out of range, a missing file, an
occupied run directory) in one line on stderr naming it, with exit status 2, before any
work and without writing anything; Ctrl-C exits with status 130. Bad input, the run
directory lock and crash safety (resume and the stage cache) are in
[Reliability](reliability.md); what a run writes is in [The run directory](run-directory.md).
"""

# What each command's help strings have no room for (Markdown, after its table).
NOTES = {
    "run": """\
* `SCENARIO`: a TOML file, or the name of a built-in scenario; `pipeline scenarios` lists
  them. The default, `paper-squares`, is the paper's reference stack (270 squares
  20 x 20 x 2 mm, 5 batches of 54, 150 mm target, released 100-200 mm up).
* `--set KEY=VALUE` changes one key of the scenario without editing its file; repeat it
  for several (a key set twice takes the last value). `KEY` is the key's dotted path as in
  [the scenario key table](scenarios.md#every-key): `deposition.chips=24`,
  `mesh.kind=conformal`, `'mesh.formats=["vtu","msh"]'`. `VALUE` is read as a TOML value
  (`24`, `1.5`, `true`, `[...]`, `"text"`), and as text when it is not one (`conformal`);
  quote text that would read as a number (`'name="2024"'`). The settings are applied to
  the file's tables before the scenario is checked, so a wrong type, a value out of range
  or an unknown key is refused by the scenario's own check, naming the key. A setting that
  changes a kind (`kind`, `chip.shape`, `mesh.kind`) drops the keys the file gave for the
  old kind that the new one does not take (`mesh.voxel_mm` when `mesh.kind` goes from
  `voxel` to `conformal`; `-v` names them); a key a setting names itself is never
  dropped. The settings are recorded in the manifest (`set`) and the resolved
  `scenario.toml`, and a changed value changes the stage cache keys as an edited file
  does.
* `--to`: the last stage to run (the first one by default); each stage runs those before
  it. `solve` needs CalculiX (`ccx`) on the PATH ([solve](solve.md)).
* `--formats`: the mesh files to write instead of the scenario's `mesh.formats`; an
  unknown name is refused with the list of valid ones.
* `--repeats N`: an ensemble of N independent runs into `DIR/repeat_K/`; the seed of
  repeat K is derived from `--seed` and K only (numpy `SeedSequence([seed, K])`), so
  repeat K is the same whatever N is, however many workers run it and in whatever order
  they finish. With `--to geometry`, `DIR/ensemble.json` holds the mean and 95 %
  confidence interval of every descriptor over the repeats (figures with confidence
  bands in `DIR/figures/`). The runs go through Dask (see [Ensembles on Dask](ensembles.md));
  each is written as it arrives. `--workers` and `--scheduler` only with `--repeats`.
* `--descriptors`: compute only these [descriptors](geometry.md); an unknown name is
  refused with the list of valid ones, before any work.
* `--out`: run again into a finished run, only the stages whose inputs changed are
  redone (see [Crash safety and the stage
  cache](reliability.md#crash-safety-and-the-stage-cache)); a non-empty directory that is
  not a run (no `manifest.json`) is refused.
* `--seed` overrides the scenario's seed; every random draw of the run comes from it and
  it is recorded in the manifest. The same seed gives bit-identical poses.
* `--quiet`: warnings and errors are still printed.
* `--overwrite`: redo every stage of an earlier run in `--out` (a directory holding
  `manifest.json`), ignoring the stage cache; any other non-empty directory, a symbolic
  link, the current directory and its parents are refused.
""",
    "scenarios": """\
One line per built-in scenario (the TOML files of `pipeline/scenarios/`), sorted by name:
its name, its kind and the first paragraph of the file's leading comment.
""",
    "sweep": """\
An ensemble at every point of a grid of scenario values, and the table of every scalar
against them: [The conveyor line and process sweeps](conveyor.md#process-sweeps).
""",
    "describe": """\
Runs the geometry stage on an existing packing run (it reads `scenario.toml` and
`packing/poses_after_batch_NN.csv` back) and adds `geometry/` to it; the folder is built
hidden and swapped in only when complete.
""",
    "compare": """\
Takes two ensemble directories and says, descriptor by descriptor, whether they differ:
difference of the means (B - A) with its Welch 95 % interval, Hedges' g, a permutation
p-value (exact or 20,000 resamples) and Welch's, and `differs` when the permutation p,
Holm-adjusted across the descriptor's scalars, is below 0.05; for every profile (layers,
batches, rings around the target centre, NEH, tilt and direction histograms, per-layer
tensors) the indices where they differ after a Holm correction across the profile.
Ensembles described with different geometry settings are refused. It prints a table and
writes `compare.json`, `compare.md` and `figures/layer_filling.png` (Fig. 12) into
`--out`.
""",
    "validate": "The cases and what they compare: [Validation](validation.md).\n",
    "diagnose": "Specs, tables and the report: [Sim-to-real diagnosis](diagnosis.md).\n",
    "synth": "What it simulates and writes: [Sim-to-real diagnosis](diagnosis.md).\n",
}


def _commands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of every command, in the parser's order."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {a.dest: a.help or "" for a in sub._choices_actions}
    return [(name, helps.get(name, ""), p) for name, p in sub.choices.items()]


def _usage(parser: argparse.ArgumentParser) -> str:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups, "")
    return formatter.format_help().strip()


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _range(action: argparse.Action) -> str | None:
    """``low to high`` of a bounded type (cli._bounded), the machine-dependent bound as
    the type states it for the reference."""
    low = getattr(action.type, "low", None)
    if low is None:
        return None
    high = action.type.high_text or _number(action.type.high)
    return f"{_number(low)} to {high}"


def _help(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    """The action's help as ``--help`` prints it, with a machine-dependent bound as the
    reference states it (``--workers``: 1 to 4 per core, not this machine's count)."""
    text = formatter._expand_help(action) if action.help else ""
    high_text = getattr(action.type, "high_text", None)
    if high_text:
        low, high = _number(action.type.low), _number(action.type.high)
        text = text.replace(f"{low} to {high}", f"{low} to {high_text}")
    return " ".join(text.split())


def _values(action: argparse.Action) -> str:
    """What the argument takes beyond its help: choices, range, repetition, a flag."""
    parts = []
    if action.choices:
        parts.append(", ".join(f"`{c}`" for c in action.choices))
    if (bounds := _range(action)) is not None:
        parts.append(bounds)
    if isinstance(action, argparse._AppendAction):
        parts.append("repeatable")
    if action.nargs == 0:
        parts.append("flag")
    if action.required and action.option_strings:
        parts.append("required")
    if action.nargs == "?":
        parts.append("optional")
    return "; ".join(parts) or "-"


def _name(action: argparse.Action) -> str:
    if not action.option_strings:
        return f"`{action.metavar or action.dest.upper()}`"
    metavar = "" if action.nargs == 0 else f" {action.metavar or action.dest.upper()}"
    return ", ".join(f"`{flag}{metavar}`" for flag in action.option_strings)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _table(parser: argparse.ArgumentParser) -> list[str]:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    rows = ["| argument | values | meaning |", "|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        rows.append(
            f"| {_name(action)} | {_cell(_values(action))} | {_cell(_help(action, formatter))} |"
        )
    return rows


def render() -> str:
    """The command-line reference, from the parser and the notes above.

    Returns
    -------
    str
        The text ``docs/cli.md`` must hold.
    """
    parser = _parser()
    commands = _commands(parser)
    unknown = set(NOTES) - {name for name, _, _ in commands}
    if unknown:  # a note of a command that is gone: a bug here, not user input
        raise RuntimeError(f"cli_docs.NOTES: no such command: {', '.join(sorted(unknown))}")
    lines = [
        "# The command line",
        "",
        "[Documentation index](index.md) · [README](../README.md)",
        "",
        "<!-- Generated by `make docs` (python -m chipstack.pipeline.cli_docs) from the "
        "parser of pipeline/cli.py: edit the help there, or the notes in "
        "pipeline/cli_docs.py, not this page. -->",
        "",
        INTRO,
        "```",
        *(f"{_usage(p)}" for _, _, p in commands),
        "```",
        "",
    ]
    for name, help_text, sub in commands:
        lines += [f"## pipeline {name}", "", f"{help_text[:1].upper()}{help_text[1:]}.", ""]
        lines += ["```", _usage(sub), "```", ""]
        if any(not isinstance(a, argparse._HelpAction) for a in sub._actions):
            lines += [*_table(sub), ""]
        if name in NOTES:
            lines += [NOTES[name]]
    while lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def write_page(page: Path = PAGE) -> bool:
    """Write the reference from the parser.

    Parameters
    ----------
    page : Path
        Where (default ``docs/cli.md``).

    Returns
    -------
    bool
        True when the page changed, False when it was current.
    """
    text = render()
    if page.is_file() and page.read_text(encoding="utf-8") == text:
        return False
    page.write_text(text, encoding="utf-8")
    return True


if __name__ == "__main__":
    import logging

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if write_page():
        logging.getLogger(__name__).info("refreshed docs/cli.md")

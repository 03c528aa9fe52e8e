"""Measured figures kept as data, and the page that shows them.

A benchmark or study records each figure it measures with :func:`record`: one JSON line
appended to ``benchmarks/results/<area>/measured.jsonl`` holding the value, its unit, the
target (where there is one), the command that measured it, and when, at which commit and
on what machine. Nothing is overwritten: the file is the figure's history.
``python -m chipstack.pipeline.measured`` (``make docs``) renders every such file, and the result
files the studies kept before (``conveyor/``, ``layers/``, ``containers/``, ``mat/``), into
``docs/measured.md``: each area's figures against their targets, then the history of the
headline figures. A test checks that the page is current, so a re-measurement changes
data and the page follows; prose elsewhere links the page instead of quoting numbers.

    from chipstack.pipeline.measured import record
    record("packing", "reference deposition, median of 5", 3.13, "s", target="<= 4",
           command="python benchmarks/bench_packing.py", headline=True)
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import statistics
import subprocess
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from chipstack.core.errors import InputError

__all__ = ["Figure", "load", "machine", "met", "record", "render", "write_page"]

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "measured.md"
FILE = "measured.jsonl"
_AREA = re.compile(r"[a-z0-9][a-z0-9-]*")
_TARGET = re.compile(
    r"^\s*(?:(?P<op><=|>=|<|>|==)\s*(?P<bound>[-+0-9.eE]+)"
    r"|(?P<low>[-+0-9.eE]+)\s+to\s+(?P<high>[-+0-9.eE]+))\s*$"
)


@dataclass(frozen=True)
class Figure:
    """One measurement of one figure (a line of a ``measured.jsonl``).

    ``target`` is ``"<= 60"``, ``"< 10"``, ``">= 1.8"``, ``"> 0"``, ``"== 0"`` or
    ``"90 to 98"`` in the figure's own unit, or empty where there is none. ``date`` is
    UTC, ISO 8601; ``commit`` the code measured (git's short hash).
    """

    area: str
    name: str
    value: float
    unit: str
    target: str
    command: str
    date: str
    commit: str
    machine: str
    note: str = ""
    headline: bool = False


def met(value: float, target: str) -> bool | None:
    """Whether ``value`` meets ``target`` (None: no target).

    >>> met(3.1, "<= 4"), met(5, "<= 4"), met(95, "90 to 98"), met(1.0, "")
    (True, False, True, None)
    """
    if not target:
        return None
    match = _TARGET.match(target)
    if match is None:
        raise InputError(
            f"target: {target!r} is not '<= X', '< X', '>= X', '> X', '== X' or 'X to Y'"
        )
    if match["op"] is None:
        return float(match["low"]) <= value <= float(match["high"])
    bound = float(match["bound"])
    return {
        "<=": value <= bound,
        "<": value < bound,
        ">=": value >= bound,
        ">": value > bound,
        "==": value == bound,
    }[match["op"]]


def machine() -> str:
    """This machine in a few words: cores, memory, architecture, system and Python."""
    memory = ""
    try:
        with open("/proc/meminfo") as info:
            kb = int(info.readline().split()[1])
        memory = f", {kb / 2**20:.1f} GB"
    except (OSError, ValueError, IndexError):
        pass
    return (
        f"{os.cpu_count()} cores{memory}, {platform.machine()}, {platform.system()} "
        f"{platform.release().split('-')[0]}, Python {platform.python_version()}"
    )


def _commit() -> str:
    try:
        done = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 else "unknown"


def record(
    area: str,
    name: str,
    value: float,
    unit: str,
    *,
    target: str = "",
    command: str = "",
    note: str = "",
    headline: bool = False,
    date: str | None = None,
    commit: str | None = None,
    machine_text: str | None = None,
    results: Path = RESULTS,
) -> Path:
    """Append one measured figure to ``results/<area>/measured.jsonl``; returns that file.

    Parameters
    ----------
    area : str
        The folder under ``benchmarks/results/``: lower case, digits and hyphens
        (``"packing"``, ``"first-run"``, ``"diagnosis"``).
    name : str
        What was measured, the same words every time it is measured again (its history
        is the records of that name), e.g. ``"reference deposition, median of 5"``.
    value : float
        The figure, in ``unit``.
    unit : str
        ``"s"``, ``"MB"``, ``"%"``, ``"x"``, ``""`` for a count or ratio, ...
    target : str, optional
        ``"<= 60"``, ``">= 95"``, ``"90 to 98"``, ... in ``unit`` (checked here).
    command : str, optional
        The command that measured it, as a user would type it.
    note : str, optional
        One line of context: the spread, the conditions (``"other core busy"``).
    headline : bool, optional
        Show its history on the page (the figures the README links).
    date, commit, machine_text : str, optional
        Default: now (UTC), git's HEAD, :func:`machine`; given for figures measured
        earlier.
    results : Path, optional
        The results folder (default: the repository's ``benchmarks/results``).

    Raises
    ------
    InputError
        A bad area, a value that is not a finite number, a target that cannot be read.
    """
    if not isinstance(area, str) or not _AREA.fullmatch(area):
        raise InputError(f"area: {area!r} must be lower case letters, digits and hyphens")
    if not isinstance(name, str) or not name.strip() or "\n" in name:
        raise InputError(f"name: {name!r} must be one non-empty line")
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"value: {value!r} is not a finite number ({name})")
    met(float(value), target)  # refuses a target it cannot read
    figure = Figure(
        area=area,
        name=name.strip(),
        value=value,
        unit=unit,
        target=target.strip(),
        command=command,
        date=date or datetime.now(UTC).isoformat(timespec="seconds"),
        commit=commit or _commit(),
        machine=machine_text or machine(),
        note=note,
        headline=headline,
    )
    folder = Path(results) / area
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / FILE
    with path.open("a", encoding="utf-8") as out:  # one line: an append is not torn
        out.write(json.dumps(asdict(figure), ensure_ascii=False) + "\n")
    return path


def load(results: Path = RESULTS) -> list[Figure]:
    """Every recorded figure under ``results``, by area, then in the order recorded."""
    figures = []
    for path in sorted(Path(results).glob(f"*/{FILE}")):
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if not line.strip():
                continue
            try:
                figures.append(Figure(**json.loads(line)))
            except (ValueError, TypeError) as exc:
                raise InputError(f"{path}:{number}: not a measured figure ({exc})") from None
    return figures


# -- the page ------------------------------------------------------------------------


def _number(value: float) -> str:
    """Four significant digits at most, thousands separated: 3.13, 182.2, 1,424."""
    if isinstance(value, int) or abs(value) >= 1000:
        return f"{round(value):,}"
    return f"{value:.4g}"


def _with_unit(value: float, unit: str) -> str:
    if not unit:
        return _number(value)
    return f"{_number(value)}{'' if unit == 'x' else ' '}{unit}"


def _target(figure: Figure) -> str:
    if not figure.target:
        return "-"
    unit = "" if not figure.unit else figure.unit if figure.unit == "x" else " " + figure.unit
    shown = figure.target + unit
    return shown.replace("<=", "&le;").replace(">=", "&ge;")


def _met(figure: Figure) -> str:
    verdict = met(float(figure.value), figure.target)
    return "-" if verdict is None else "met" if verdict else "**not met**"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _day(date: str) -> str:
    return date[:10]


def _latest(figures: Iterable[Figure]) -> dict[str, Figure]:
    """The newest record of every figure name (by date; ties: the later line)."""
    newest: dict[str, Figure] = {}
    for figure in figures:
        if figure.name not in newest or figure.date >= newest[figure.name].date:
            newest[figure.name] = figure
    return newest


def _figures_section(figures: list[Figure]) -> list[str]:
    lines = []
    by_area: dict[str, list[Figure]] = defaultdict(list)
    for figure in figures:
        by_area[figure.area].append(figure)
    for area in sorted(by_area):
        lines += [
            f"### {area}",
            "",
            "| figure | measured | target | | when | commit | command |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, f in _latest(by_area[area]).items():
            note = f" ({_cell(f.note)})" if f.note else ""
            lines.append(
                f"| {_cell(name)} | {_with_unit(f.value, f.unit)}{note} | {_target(f)} | "
                f"{_met(f)} | {_day(f.date)} | `{f.commit}` | "
                f"{'`' + _cell(f.command) + '`' if f.command else '-'} |"
            )
        lines.append("")
    return lines


def _history_section(figures: list[Figure]) -> list[str]:
    headline = sorted({(f.area, f.name) for f in figures if f.headline})
    lines = []
    for area, name in headline:
        rows = sorted(
            (f for f in figures if f.area == area and f.name == name), key=lambda f: f.date
        )
        lines += [
            f"### {area}: {name}",
            "",
            "| when | measured | | commit | machine | conditions |",
            "|---|---|---|---|---|---|",
        ]
        for f in rows:
            lines.append(
                f"| {f.date.replace('T', ' ').removesuffix('+00:00')} | "
                f"{_with_unit(f.value, f.unit)} | {_met(f)} | `{f.commit}` | "
                f"{_cell(f.machine)} | {_cell(f.note) or '-'} |"
            )
        lines.append("")
    return lines


def _json_files(folder: Path) -> list[dict]:
    rows = []
    for path in sorted(folder.glob("*.json")):
        try:
            rows.append(json.loads(path.read_text()))
        except ValueError:
            continue
    return rows


def _kept_conveyor(results: Path) -> list[str]:
    rows = sorted(_json_files(results / "conveyor"), key=lambda r: r.get("chips", 0))
    if not rows:
        return []
    lines = [
        "### conveyor: mats of a 440 x 540 mm panel's line (`benchmarks/results/conveyor/`)",
        "",
        "`python benchmarks/bench_packing.py --conveyor 300 3000 30000`, one process per mat; "
        "targets: 3,000 chips &le; 60 s, ms per chip at 30,000 within 1.2x that at 300.",
        "",
        "| chips | wall time | ms per chip | simulated | most chips in the engine | peak memory |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['chips']:,} | {r['wall_s']:,.1f} s | {r['ms_per_chip']:.1f} | "
            f"{r['sim_s']:.1f} s | {r['most_in_engine']:,} | {r['peak_mb']:.0f} MB |"
        )
    return lines + [""]


def _spread(values: list[float], digits: int) -> str:
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return (
        f"{statistics.mean(values):.{digits}f} ({min(values):.{digits}f} to "
        f"{max(values):.{digits}f})"
    )


def _kept_layers(results: Path) -> list[str]:
    groups: dict[str, list[dict]] = defaultdict(list)
    for path in sorted((results / "layers").glob("*.json")):
        groups[path.stem.rsplit("-seed", 1)[0]].append(json.loads(path.read_text()))
    if not groups:
        return []
    lines = [
        "### layers: the paper's layer filling (`benchmarks/results/layers/`)",
        "",
        "`python benchmarks/bench_layers.py`: the 270-chip stack, highest non-empty 2 mm "
        "layer (the paper: 13) and mean chip-centre height, mean (min to max) over seeds.",
        "",
        "| preset and contact parameters | seeds | highest filled layer | mean centre height |",
        "|---|---|---|---|",
    ]
    for name in sorted(groups):
        runs = groups[name]
        lines.append(
            f"| {name} | {len(runs)} | {_spread([r['highest_filled'] for r in runs], 1)} | "
            f"{_spread([r['mean_centre_mm'] for r in runs], 2)} mm |"
        )
    return lines + [""]


def _kept_containers(results: Path) -> list[str]:
    groups: dict[str, list[dict]] = defaultdict(list)
    for path in sorted((results / "containers").glob("*.json")):
        groups[path.stem.split("-seed", 1)[0]].append(json.loads(path.read_text()))
    if not groups:
        return []
    lines = [
        "### containers: rods poured into cylinders (`benchmarks/results/containers/`)",
        "",
        "`python benchmarks/bench_containers.py`: packing fraction of the rods inside "
        "the container, mean (min to max) over seeds (aspect ratio 25: measured 18 %, the "
        "paper's model 14.8 %).",
        "",
        "| case | seeds | packing fraction | contacts per rod | wall time per fill |",
        "|---|---|---|---|---|",
    ]
    for name in sorted(groups):
        runs = groups[name]
        lines.append(
            f"| {name} | {len(runs)} | {_spread([100 * r['phi'] for r in runs], 1)} % | "
            f"{_spread([r['contacts_per_rod'] for r in runs], 2)} | "
            f"{_spread([r['seconds'] for r in runs], 0)} s |"
        )
    return lines + [""]


def _kept_mat(results: Path) -> list[str]:
    groups: dict[str, list[dict]] = defaultdict(list)
    for path in sorted((results / "mat").glob("*.json")):
        groups[path.stem.rsplit("-", 1)[0]].append(json.loads(path.read_text()))
    if not groups:
        return []
    lines = [
        "### mat: the fibre mat (`benchmarks/results/mat/`)",
        "",
        "`python benchmarks/bench_mat.py`: fibres seen from the top over the target, "
        "mean (min to max) over seeds.",
        "",
        "| preset | seeds | fibres seen from the top | top of the mat | wall time |",
        "|---|---|---|---|---|",
    ]
    for name in sorted(groups):
        runs = groups[name]
        lines.append(
            f"| {name} | {len(runs)} | "
            f"{_spread([r['fraction_over_target_top_pct'] for r in runs], 1)} % | "
            f"{_spread([r['top_mm'] for r in runs], 1)} mm | "
            f"{_spread([r['seconds'] for r in runs], 0)} s |"
        )
    return lines + [""]


def _kept_other(results: Path) -> list[str]:
    """Result files kept as text: listed with a link."""
    skip = {"diagnosis", "diagnosis-stacks"}  # the diagnosis's own: docs/diagnosis.md
    found = sorted(
        f"benchmarks/results/{p.relative_to(results).as_posix()}"
        for p in Path(results).glob("*/*")
        if p.suffix in (".txt", ".md") and p.parent.name not in skip
    )
    if not found:
        return []
    lines = ["### Other results kept as text", ""]
    lines += [f"- [`{name}`](../{name})" for name in found]
    return lines + [""]


def render(results: Path = RESULTS) -> str:
    """``docs/measured.md`` from the figures and result files under ``results``."""
    figures = load(results)
    lines = [
        "# Measured",
        "",
        "[Documentation index](index.md) · [README](../README.md)",
        "",
        "<!-- Generated by `make docs` (python -m chipstack.pipeline.measured) from "
        "benchmarks/results/: edit the data, not this page. -->",
        "",
        "Every figure here is data: a benchmark or study appends it to "
        "`benchmarks/results/<area>/measured.jsonl` (`pipeline.measured.record`: value, "
        "unit, target, command, date, commit, machine), and `make docs` renders this page "
        "from those files. A test fails when the page is not current. Figures recorded "
        "before they were data carry the date and commit of the page that first stated "
        "them. This machine's speed varies by up to a factor of 1.5 over a day: compare "
        "figures measured side by side, not across days.",
        "",
        "## Latest figures against their targets",
        "",
        *_figures_section(figures),
        "## History of the headline figures",
        "",
        *_history_section(figures),
        "## Results the studies keep as files",
        "",
        *_kept_conveyor(results),
        *_kept_layers(results),
        *_kept_containers(results),
        *_kept_mat(results),
        *_kept_other(results),
    ]
    while lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def write_page(results: Path = RESULTS, page: Path = PAGE) -> bool:
    """Write ``page`` from ``results``; True when it changed."""
    text = render(results)
    if page.is_file() and page.read_text(encoding="utf-8") == text:
        return False
    page.write_text(text, encoding="utf-8")
    return True


if __name__ == "__main__":
    import logging

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if write_page():
        logging.getLogger(__name__).info("refreshed docs/measured.md")

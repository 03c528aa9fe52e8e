"""`pipeline compare RUN_A RUN_B`: do two ensembles of stacks differ, descriptor by descriptor?"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from chipstack.core.errors import InputError
from chipstack.core.files import read_json
from chipstack.core.schema import printable
from chipstack.pipeline.rundir import RunDirectory

__all__ = ["load_ensemble", "compare_runs", "comparison_table"]


def load_ensemble(path: str | Path) -> dict[str, Any]:
    """The ``ensemble.json`` of an ensemble run directory (``pipeline run --repeats N``)."""
    folder = Path(path)
    shown = printable(path)
    if not folder.is_dir():
        raise InputError(f"{shown}: no such run directory")
    file = folder / "ensemble.json"
    if not file.is_file():
        if (folder / "geometry" / "descriptors.json").is_file():
            raise InputError(
                f"{shown}: a single run; compare needs ensembles (pipeline run --repeats N)"
            )
        raise InputError(
            f"{shown}: no ensemble.json (run `pipeline run SCENARIO --to geometry --repeats N`)"
        )
    data = read_json(file, "ensemble file")
    problem = _ensemble_problem(data)
    if problem:
        raise InputError(f"{file}: not a valid ensemble file ({problem})")
    return data


def _is_number(value: Any) -> bool:
    return value is None or (isinstance(value, int | float) and not isinstance(value, bool))


def _ensemble_problem(data: Any) -> str | None:
    """What makes ``data`` unusable as an ensemble summary, or None."""
    if not isinstance(data, dict):
        return "not a JSON object"
    repeats = data.get("repeats")
    if not isinstance(repeats, int) or isinstance(repeats, bool) or repeats < 1:
        return "repeats must be a positive integer"
    descriptors = data.get("descriptors")
    if not isinstance(descriptors, dict):
        return "descriptors must be an object"
    if not isinstance(data.get("parameters", {}), dict):
        return "parameters must be an object"
    for name, section in descriptors.items():
        if not isinstance(section, dict):
            return f"descriptor {name!r} must be an object"
        for key, entry in (section.get("scalars") or {}).items():
            values = entry.get("values") if isinstance(entry, dict) else None
            if not isinstance(values, list) or len(values) != repeats:
                return f"{name}.{key}: values must list one number per repeat"
            if not all(_is_number(v) for v in values) or not isinstance(entry.get("unit"), str):
                return f"{name}.{key}: values must be numbers and unit a string"
        for key, entry in (section.get("profiles") or {}).items():
            if not isinstance(entry, dict):
                return f"{name}.{key}: must be an object"
            index, rows = entry.get("index"), entry.get("values")
            if not isinstance(index, list) or not isinstance(rows, list) or len(rows) != repeats:
                return f"{name}.{key}: needs an index and one row of values per repeat"
            for row in rows:
                if not isinstance(row, list) or len(row) != len(index):
                    return f"{name}.{key}: every row must have one value per index"
                if not all(_is_number(v) for v in row):
                    return f"{name}.{key}: values must be numbers"
            if not isinstance(entry.get("unit"), str) or not isinstance(
                entry.get("index_name"), str
            ):
                return f"{name}.{key}: unit and index_name must be strings"
    return None


def comparison_table(result: dict[str, Any], labels: tuple[str, str]) -> str:
    """A Markdown table: one row per scalar descriptor, and the profiles' carrying indices."""
    a, b = labels
    lines = [
        f"| descriptor | {a} mean | {b} mean | difference (95 % CI) | Hedges g | p (perm.) "
        "| p (Holm) | p (Welch) | differs |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def f(v: float | None, digits: int = 4) -> str:
        return "-" if v is None else f"{v:.{digits}g}"

    for name, section in result["descriptors"].items():
        for key, c in section["scalars"].items():
            lines.append(
                f"| {name}.{key} | {f(c['mean_a'])} | {f(c['mean_b'])} | "
                f"{f(c['difference'])} ({f(c['ci_low'])} to {f(c['ci_high'])}) | "
                f"{f(c['hedges_g'], 3)} | {f(c['p_permutation'], 3)} | {f(c['p_holm'], 3)} | "
                f"{f(c['p_welch'], 3)} | "
                f"{'yes' if c['differs'] else 'no'} |"
            )
    lines += ["", "| profile | differs at (Holm-adjusted p < alpha) |", "|---|---|"]
    for name, section in result["descriptors"].items():
        for key, p in section["profiles"].items():
            where = ", ".join(str(i) for i in p["carried_by"]) or "nowhere"
            lines.append(f"| {name}.{key} | {p['index_name']}: {where} |")
    return "\n".join(lines) + "\n"


def compare_runs(
    run_a: str | Path,
    run_b: str | Path,
    out: str | Path,
    overwrite: bool = False,
    command: list[str] | None = None,
) -> tuple[dict[str, Any], str]:
    """Compare two ensembles; writes compare.json, compare.md and Fig. 12 into ``out``."""
    run = RunDirectory(out, overwrite=overwrite)
    run.check()
    ensembles = (load_ensemble(run_a), load_ensemble(run_b))
    # Imported once the inputs are checked: scipy.stats and matplotlib take ~1.5 s, too
    # long to wait for a one-line error about a missing directory.
    from chipstack.geometry.ensemble import compare_ensembles
    from chipstack.geometry.run_figures import comparison_figures

    labels = (Path(run_a).name or str(run_a), Path(run_b).name or str(run_b))
    if labels[0] == labels[1]:
        labels = (f"A: {labels[0]}", f"B: {labels[1]}")
    result = compare_ensembles(*ensembles)
    result["a"] = {"path": str(run_a), "repeats": ensembles[0]["repeats"]}
    result["b"] = {"path": str(run_b), "repeats": ensembles[1]["repeats"]}
    table = comparison_table(result, labels)
    with run:
        run.write_json("compare.json", result)
        run.write_text("compare.md", f"# {labels[0]} vs {labels[1]}\n\n" + table)
        files = comparison_figures(run.path("figures/x").parent, labels, ensembles)
        run.write_json(
            "manifest.json",
            {
                "tool": "chipstack",
                "kind": "comparison",
                "command": command or [],
                "a": str(run_a),
                "b": str(run_b),
                "files": ["compare.json", "compare.md", *files],
                "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            },
        )
    return result, table

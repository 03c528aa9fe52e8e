"""Ensembles of described stacks: means with confidence intervals, and comparisons.

Works on the JSON sections written by :func:`geometry.describe.Description.to_json` (one
per repeat), so an ensemble can be summarised or compared long after its runs finished.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.core.errors import InputError
from chipstack.geometry.run_figures import ensemble_figures
from chipstack.geometry.stats import compare, holm, summarize

__all__ = ["ENSEMBLE_SCHEMA", "summarize_runs", "compare_ensembles", "ALPHA"]

ENSEMBLE_SCHEMA = "chipstack.ensemble/1"
ALPHA = 0.05


def _summary(values: list[float]) -> dict[str, Any]:
    if not values:
        return {"n": 0, "mean": None, "sd": None, "ci_low": None, "ci_high": None}
    s = summarize(values)

    def clean(v: float) -> float | None:
        return float(v) if np.isfinite(v) else None

    return {
        "n": s.n,
        "mean": clean(s.mean),
        "sd": clean(s.sd),
        "ci_low": clean(s.ci_low),
        "ci_high": clean(s.ci_high),
    }


def _aligned(profiles: list[dict[str, Any]]) -> tuple[list[Any], list[list[float | None]]]:
    """Common index of one profile across runs, and each run's values on it (padded)."""
    index: list[Any] = []
    for p in profiles:
        for i in p["index"]:
            if i not in index:
                index.append(i)
    if all(isinstance(i, int | float) for i in index):
        index.sort()
    rows = []
    for p in profiles:
        lookup = dict(zip(p["index"], p["values"], strict=True))
        pad = p.get("pad")
        if pad == "last":  # cumulative profiles keep their final value above the top
            pad = p["values"][-1] if p["values"] else None
        rows.append([lookup.get(i, pad) for i in index])
    return index, rows


def summarize_runs(sections: Sequence[dict[str, Any]], seeds: Sequence[int]) -> dict[str, Any]:
    """Mean, sd and 95 % confidence interval of every scalar and profile over the runs.

    ``sections``: the runs' ``descriptors.json`` contents, in repeat order.
    """
    if not sections:
        raise InputError("sections: no run to summarise")
    descriptors: dict[str, Any] = {}
    names = sections[0]["descriptors"]
    for name, first in names.items():
        runs = [s["descriptors"].get(name) for s in sections]
        if any(r is None for r in runs):
            raise InputError(f"descriptor {name!r}: missing from some runs of the ensemble")
        scalars = {}
        for key, meta in first["scalars"].items():
            values = [r["scalars"][key]["value"] for r in runs]
            finite = [float(v) for v in values if v is not None]
            scalars[key] = {
                "unit": meta["unit"],
                "doc": meta["doc"],
                "values": values,
                **_summary(finite),
            }
        profiles = {}
        for key, meta in first["profiles"].items():
            index, rows = _aligned([r["profiles"][key] for r in runs])
            columns = list(zip(*rows, strict=True)) if rows and index else []
            stats = [_summary([float(v) for v in col if v is not None]) for col in columns]
            profiles[key] = {
                "index_name": meta["index_name"],
                "index": index,
                "pad": meta.get("pad"),
                "unit": meta["unit"],
                "doc": meta["doc"],
                "values": rows,
                **{k: [s[k] for s in stats] for k in ("n", "mean", "sd", "ci_low", "ci_high")},
            }
        descriptors[name] = {"scalars": scalars, "profiles": profiles}
    return {
        "schema": ENSEMBLE_SCHEMA,
        "repeats": len(sections),
        "seeds": list(seeds),
        "parameters": sections[0].get("parameters", {}),
        "confidence": 0.95,
        "descriptors": descriptors,
    }


def _comparison(a: list[float], b: list[float], seed: int) -> dict[str, Any]:
    c = compare(a, b, seed=seed)
    out = {
        "mean_a": c.mean_a,
        "mean_b": c.mean_b,
        "difference": c.difference,
        "ci_low": c.ci_low,
        "ci_high": c.ci_high,
        "hedges_g": c.hedges_g,
        "p_welch": c.p_welch,
        "p_permutation": c.p_permutation,
    }
    return {k: (float(v) if np.isfinite(v) else None) for k, v in out.items()}


def compare_ensembles(
    a: dict[str, Any], b: dict[str, Any], seed: int = 0, alpha: float = ALPHA
) -> dict[str, Any]:
    """Descriptor by descriptor: do two ensembles differ, and where.

    For every scalar: difference of means (b - a) with its Welch 95 % interval, Hedges' g,
    Welch and permutation p-values, the permutation p Holm-adjusted across the
    descriptor's scalars, and ``differs`` (adjusted p < alpha). Ensembles described with
    different geometry settings are refused. For every
    profile: the same per index, with Holm-adjusted permutation p-values across the
    profile's indices, and ``carried_by``: the indices (layers, rings, batches) whose
    adjusted p is below alpha.
    """
    for label, ensemble in (("A", a), ("B", b)):
        if ensemble.get("repeats", 0) < 2:
            raise InputError(f"ensemble {label}: needs at least 2 repeats to be compared")
    pa, pb = a.get("parameters", {}), b.get("parameters", {})
    differ = sorted(k for k in set(pa) | set(pb) if pa.get(k) != pb.get(k))
    if differ:
        shown = ", ".join(f"{k} {pa.get(k)} vs {pb.get(k)}" for k in differ)
        raise InputError(f"ensembles described with different geometry settings ({shown})")
    common = [name for name in a["descriptors"] if name in b["descriptors"]]
    if not common:
        raise InputError("ensembles A and B share no descriptor to compare")
    out: dict[str, Any] = {}
    for name in a["descriptors"]:
        if name not in b["descriptors"]:
            continue
        da, db = a["descriptors"][name], b["descriptors"][name]
        scalars = {}
        for key, meta in da["scalars"].items():
            if key not in db["scalars"]:
                continue
            va = [v for v in meta["values"] if v is not None]
            vb = [v for v in db["scalars"][key]["values"] if v is not None]
            if len(va) < 2 or len(vb) < 2:
                continue
            result = _comparison(va, vb, seed)
            result["unit"] = meta["unit"]
            scalars[key] = result
        # One family per descriptor: its scalars are tested together (Holm).
        raw = [
            c["p_permutation"] if c["p_permutation"] is not None else 1.0 for c in scalars.values()
        ]
        for c, p in zip(scalars.values(), holm(raw) if raw else [], strict=True):
            c["p_holm"] = float(p)
            c["differs"] = bool(p < alpha)
        profiles = {}
        for key, meta in da["profiles"].items():
            if key not in db["profiles"]:
                continue
            mb = db["profiles"][key]
            merged_index, rows = _aligned(
                [
                    {"index": meta["index"], "values": r, "pad": meta.get("pad")}
                    for r in meta["values"]
                ]
                + [{"index": mb["index"], "values": r, "pad": mb.get("pad")} for r in mb["values"]]
            )
            na = len(meta["values"])
            per_index = []
            for j, i in enumerate(merged_index):
                va = [r[j] for r in rows[:na] if r[j] is not None]
                vb = [r[j] for r in rows[na:] if r[j] is not None]
                if len(va) < 2 or len(vb) < 2:
                    continue
                per_index.append({"index": i, **_comparison(va, vb, seed)})
            raw = [c["p_permutation"] if c["p_permutation"] is not None else 1.0 for c in per_index]
            adjusted = holm(raw) if raw else []
            for c, p in zip(per_index, adjusted, strict=True):
                c["p_holm"] = float(p)
            profiles[key] = {
                "index_name": meta["index_name"],
                "unit": meta["unit"],
                "comparisons": per_index,
                "carried_by": [c["index"] for c in per_index if c["p_holm"] < alpha],
            }
        out[name] = {"scalars": scalars, "profiles": profiles}
    return {"alpha": alpha, "test": "permutation of the difference of means", "descriptors": out}


def summarize_repeats(folders: Sequence[Path], seeds: Sequence[int]) -> dict[str, Any]:
    """Mean and 95 % confidence interval of every descriptor over the repeats."""
    sections = [json.loads((f / "descriptors.json").read_text()) for f in folders]
    summary = summarize_runs(sections, list(seeds))
    summary["runs"] = [f.parent.name for f in folders]
    return summary


def write_repeats(summary: dict[str, Any], path) -> None:
    """The ensemble's statistics (``ensemble.json``) and their figures."""
    path("ensemble.json").write_text(json.dumps(summary, indent=2) + "\n")
    ensemble_figures(path("figures/x").parent, summary)

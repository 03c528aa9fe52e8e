"""Which next drop experiment would tell tied models apart best: for twice the drops and
for a few extra releases, the cross-validated accuracy among the tied models on simulated
datasets of the design with it, against the design as it is; scored once per design and
kept in the table store.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import sklearn

from chipstack.diagnosis.model import Condition, Experiment
from chipstack.diagnosis.model_choice import (
    MODEL_CHOICE_VERSION,
    _cross_validated,
    _quiet_parallel,
)
from chipstack.diagnosis.reference_table import (
    DEFAULT_POOL_DROPS,
    ReferenceTable,
    TableStore,
    pool_drops_for,
    simulation_key,
)
from chipstack.diagnosis.summaries import design_summaries
from chipstack.packing.drop import DropProtocol

__all__ = ["NEXT_CANDIDATES", "NEXT_MIN_GAIN", "NEXT_RELEASES", "NEXT_TREES", "next_experiment"]

# Releases a next experiment may add (height mm, yaw deg), tried in this order; the design's
# own releases are skipped. Three are scored (each costs the tied models' pools there).
NEXT_RELEASES = ((1000.0, 0.0), (150.0, 0.0), (700.0, 45.0), (300.0, 15.0), (500.0, 30.0))
NEXT_CANDIDATES = 3
NEXT_TREES = 100
NEXT_MIN_GAIN = 0.03  # below this gain in accuracy no next experiment is named


@_quiet_parallel
def next_experiment(
    experiment: Experiment,
    drops: dict[str, int],
    tied: list[str],
    counts: dict[str, int],
    order: int,
    has_yaw: bool,
    has_tilt: bool,
    store: TableStore,
    run_many: Callable[[Callable, list[dict]], list],
    progress: Callable[[str], None],
    seed: int = 0,
) -> dict:
    """Which extra condition would tell the ``tied`` models apart best
    (:func:`_score_next_experiment`), kept in ``store`` by a key of the design, the tied
    models and their pools, so that a second diagnosis of the design scores nothing."""
    text = json.dumps(
        dict(
            version=MODEL_CHOICE_VERSION,
            sklearn=sklearn.__version__,
            simulation=simulation_key(experiment.scenario),
            conditions=[
                [c.protocol.height_mm, c.protocol.yaw_deg, c.protocol.tilt_deg]
                for c in experiment.conditions
            ],
            release_tilt=experiment.settings.release_tilt,
            drops=[drops[c.name] for c in experiment.conditions],
            noise=[experiment.position_sd_mm, experiment.angle_sd_deg],
            angles=[has_yaw, has_tilt],
            tied=list(tied),
            pools=[counts[m] for m in tied],
            seed=seed,
            scored=[NEXT_RELEASES, NEXT_CANDIDATES, NEXT_TREES, NEXT_MIN_GAIN, DEFAULT_POOL_DROPS],
        ),
        sort_keys=True,
    )
    name = f"next-{hashlib.sha256(text.encode()).hexdigest()[:20]}.json"
    blob = store.load(name)
    if blob is not None:
        progress("model choice: next experiment scored before")
        return json.loads(blob)
    result = _score_next_experiment(
        experiment, drops, tied, counts, order, has_yaw, has_tilt, store, run_many, progress, seed
    )
    store.save(name, json.dumps(result).encode())
    return result


def _score_next_experiment(
    experiment: Experiment,
    drops: dict[str, int],
    tied: list[str],
    counts: dict[str, int],
    order: int,
    has_yaw: bool,
    has_tilt: bool,
    store: TableStore,
    run_many: Callable[[Callable, list[dict]], list],
    progress: Callable[[str], None],
    seed: int = 0,
) -> dict:
    """Which extra condition would tell the ``tied`` models apart best: for each candidate
    release (and for twice the drops in every condition) the cross-validated accuracy
    among the tied models on simulated datasets of the design with it, against the
    design as it is. The candidates' pools share the tied models' strengths pool by pool
    (the same Halton draws), so a dataset of the design and one of the extra condition
    come from one setting."""
    n = int(np.median(list(drops.values())))
    pool_drops = pool_drops_for(drops)
    tied_counts = {m: counts[m] for m in tied}
    base = ReferenceTable(experiment, tied, store, pool_drops)
    base.load()
    base.ensure(tied_counts, run_many, progress)
    rng = np.random.default_rng([seed, 61])

    def features(table, x, want) -> dict[tuple, np.ndarray]:
        out = {}
        for d in table.datasets(tied_counts, want, rng):
            if d.part >= 0:
                key = (d.setting.model, d.setting.index, d.part)
                out[key] = design_summaries(d.drops, x, order, has_yaw, has_tilt)
        return out

    def accuracy(keys: list[tuple], blocks: list[dict]) -> float:
        X = np.array([np.concatenate([b[k] for b in blocks]) for k in keys])
        y = np.array([tied.index(k[0]) for k in keys])
        groups = np.array([tied.index(k[0]) * 10_000 + k[1] for k in keys])
        votes = _cross_validated(X, y, groups, len(tied), seed, trees=NEXT_TREES)
        return float(np.mean(votes.argmax(axis=1) == y))

    now = features(base, experiment, drops)
    options = []
    # Twice the drops in every condition, from the same pools.
    if 2 * max(drops.values()) <= pool_drops:
        doubled = features(base, experiment, {c: 2 * d for c, d in drops.items()})
        keys = sorted(set(doubled))
        options.append(
            dict(
                kind="more drops",
                drops_per_condition=2 * n,
                accuracy_after=accuracy(keys, [doubled]),
                accuracy_now=accuracy(keys, [{k: now[k] for k in keys}]),
            )
        )
    have = {(c.protocol.height_mm, c.protocol.yaw_deg) for c in experiment.conditions}
    releases = [r for r in NEXT_RELEASES if r not in have][:NEXT_CANDIDATES]
    tilt = experiment.conditions[0].protocol.tilt_deg
    for height, yaw in releases:
        name = f"next-h{height:g}-yaw{yaw:g}"
        condition = Condition(name, DropProtocol(height_mm=height, yaw_deg=yaw, tilt_deg=tilt))
        extra_x = replace(experiment, conditions=(condition,))
        extra = ReferenceTable(extra_x, tied, store, max(DEFAULT_POOL_DROPS // 2, 2 * n))
        extra.load()
        progress(f"model choice: scoring a next experiment at {height:g} mm, yaw {yaw:g} deg")
        extra.ensure(tied_counts, run_many, progress)
        added = features(extra, extra_x, {name: n})
        keys = sorted(set(added) & set(now))
        options.append(
            dict(
                kind="extra condition",
                height_mm=height,
                yaw_deg=yaw,
                drops_per_condition=n,
                accuracy_after=accuracy(keys, [{k: now[k] for k in keys}, added]),
                accuracy_now=accuracy(keys, [{k: now[k] for k in keys}]),
            )
        )
    best = max(options, key=lambda o: o["accuracy_after"] - o["accuracy_now"])
    gain = best["accuracy_after"] - best["accuracy_now"]
    release = dict(height_mm=None, yaw_deg=None)
    if gain < NEXT_MIN_GAIN:
        heights = ", ".join(f"{o['height_mm']:g} mm" for o in options if "height_mm" in o)
        text = (
            f"Next experiment: none of the {len(options)} scored (twice the drops, or a "
            f"condition at {heights}) "
            f"tells {', '.join(tied)} apart better than the design does now "
            f"({100 * best['accuracy_now']:.0f} % on simulated datasets)."
        )
        return dict(
            separates=list(tied),
            options=options,
            chosen=None,
            drops_needed_per_condition=None,
            text=text,
            **release,
        )
    if best["kind"] == "more drops":
        what = f"{best['drops_per_condition']} drops in every condition instead of {n}"
    else:
        what = (
            f"a condition released at {best['height_mm']:g} mm, yaw {best['yaw_deg']:g} deg, "
            f"with {n} drops"
        )
        release = dict(height_mm=best["height_mm"], yaw_deg=best["yaw_deg"])
    text = (
        f"Next experiment: {what}. Among {', '.join(tied)}, simulated datasets of the design "
        f"are then given the right model {100 * best['accuracy_after']:.0f} % of the time, "
        f"against {100 * best['accuracy_now']:.0f} % now."
    )
    return dict(
        separates=list(tied),
        options=options,
        chosen=best,
        drops_needed_per_condition=best["drops_per_condition"],
        text=text,
        **release,
    )

"""Layer filling of the reference stack against the paper's Fig. 10, per physics preset.

The paper (section 3.1.3, Fig. 10): 270 square chips 20 x 20 x 2 mm, layers 2 mm thick,
a chip counted in the layer holding its centre of mass; "an empty layer ... is the case
for layers 14 and above" (its layers numbered from 1, so its highest filled layer is the
13th, z 24 to 26 mm). Ours are numbered from 0 (``geometry.layers``): layer k spans
[2k, 2k + 2) mm, so the paper's 13th layer is our layer 12.

For each preset (``physics.preset``: ``default``, the project's calibrated contact model;
``paper``, the paper's fitted PyBullet parameters, Table 1), or a preset with one
parameter set to the other's (``--variants "paper,friction=0.5"``), and each seed, deposits the
reference stack and records the chips per layer, the highest filled layer and the mean
centre height. Every finished stack is cached as one JSON file under
``benchmarks/results/layers/`` (a rerun skips it), and the table printed at the end gives
per preset the mean and the 95 % interval (t) over the seeds.

    .venv/bin/python benchmarks/bench_layers.py --seeds 0 1 2 3 4 5 6 7 8 9
    .venv/bin/python benchmarks/bench_layers.py --variants "paper,friction=0.5" \
        "paper,restitution=0.3" "default,friction=1.0" "default,restitution=1.0"
    .venv/bin/python benchmarks/bench_layers.py --summary-only
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np
from scipy import stats

RESULTS = Path(__file__).resolve().parent / "results" / "layers"
PRESETS = ("default", "paper")
# Which of the paper preset's parameters explains the height: each variant changes one
# (physics.friction or physics.restitution) to the other preset's value.
VARIANTS = (
    "default",
    "paper",
    "paper,friction=0.5",
    "paper,restitution=0.3",
    "default,friction=1.0",
    "default,restitution=1.0",
)
PAPER_HIGHEST_FILLED = 12  # the paper's 13th layer, numbered from 0 as ours
FULL_LAYER = 56.25  # 150 x 150 mm target / 20 x 20 mm chip


def source_commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def physics_of(variant: str) -> dict:
    """``preset[,key=value...]`` as the scenario's [physics] section."""
    preset, *overrides = variant.split(",")
    physics: dict = {"preset": preset}
    for item in overrides:
        key, value = item.split("=")
        physics[key] = float(value)
    return physics


def one_stack(variant: str, seed: int) -> dict:
    from chipstack.geometry.layers import layer_counts
    from chipstack.packing import deposit, scenario_from_dict

    start = time.perf_counter()
    stack = deposit(scenario_from_dict({"seed": seed, "physics": physics_of(variant)}))
    seconds = time.perf_counter() - start
    z = np.asarray(stack.positions)[:, 2]
    counts = layer_counts(z, 2.0)
    return dict(
        preset=variant,
        seed=seed,
        chips=int(len(z)),
        counts=[int(c) for c in counts],
        highest_filled=int(np.flatnonzero(counts).max()),
        mean_centre_mm=float(z.mean()),
        seconds=round(seconds, 2),
        commit=source_commit(),
    )


def mean_interval(values) -> tuple[float, float, float]:
    values = np.asarray(values, dtype=float)
    mean = float(values.mean())
    if len(values) < 2:
        return mean, float("nan"), float("nan")
    half = float(stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values)))
    return mean, mean - half, mean + half


def summary(records: list[dict]) -> None:
    for preset in VARIANTS:
        runs = sorted((r for r in records if r["preset"] == preset), key=lambda r: r["seed"])
        if not runs:
            continue
        highest = [r["highest_filled"] for r in runs]
        m, lo, hi = mean_interval(highest)
        centre = mean_interval([r["mean_centre_mm"] for r in runs])
        print(
            f"preset {preset}: {len(runs)} stacks; highest filled layer (from 0) mean {m:.1f} "
            f"[{lo:.1f}, {hi:.1f}], range {min(highest)} to {max(highest)} (paper: "
            f"{PAPER_HIGHEST_FILLED}); mean centre height {centre[0]:.2f} mm "
            f"[{centre[1]:.2f}, {centre[2]:.2f}]"
        )
        width = max(len(r["counts"]) for r in runs)
        table = np.zeros((len(runs), width))
        for k, r in enumerate(runs):
            table[k, : len(r["counts"])] = r["counts"]
        cells = []
        for layer in range(width):
            m, lo, hi = mean_interval(table[:, layer])
            cells.append(f"{layer}: {m:.1f} [{lo:.1f}, {hi:.1f}]")
        print("  chips per layer (mean [95 %]): " + "; ".join(cells))
        print(
            f"  a full layer: {FULL_LAYER} chips; layer 0 holds "
            f"{table[:, 0].mean() / FULL_LAYER:.0%} of one"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument(
        "--variants", nargs="+", default=list(PRESETS), help=f"of {', '.join(VARIANTS)}"
    )
    parser.add_argument("--summary-only", action="store_true")
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if not args.summary_only:
        for preset in args.variants:
            for seed in args.seeds:
                stem = preset.replace(",", "_").replace("=", "")
                path = RESULTS / f"{stem}-seed{seed}.json"
                if path.exists():
                    continue
                record = one_stack(preset, seed)
                path.write_text(json.dumps(record, indent=1) + "\n")
                print(
                    f"{preset} seed {seed}: highest filled layer {record['highest_filled']}, "
                    f"counts {record['counts']} ({record['seconds']} s)",
                    flush=True,
                )
    summary([json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))])


if __name__ == "__main__":
    main()

"""Container fills (the paper's section 5): wall time, volume fraction and contacts.

For each aspect ratio asked for (10: ``container-ar10``, 25: ``container-ar25``), fills
the container with each seed on one core and prints, per fill, the wall time, the rods
poured and inside, the volume fraction (centres of mass inside, as the paper counts),
phi * L / D and the mean number of rod-rod contacts per rod inside; then the mean, sd
and 95 % interval over the seeds beside the paper's model and Freeman et al.'s
measurement. Targets: AR 25 <= 5 min, AR 10 <= 2 min per fill.

``--compare-dynamic`` fills each container twice per seed, with settled rods frozen (the
default) and with every rod kept dynamic (``settling.freeze = false``, the reference the
freezing must reproduce), and prints both beside the difference of their means and the
pooled sd. ``--height`` sets the container's height in rod lengths (the paper's 4) and
``--ar`` any aspect ratio (rods 2 mm across): a small container keeps the dynamic fills
affordable. Besides the paper's fraction, the lower half's fraction (rods whose centre lies
in the lower half of the container) is printed: it does not depend on the one rod that
ends the fill by reaching the rim.

    .venv/bin/python benchmarks/bench_containers.py [--ar 10 25] [--seeds 0 1 2]
    .venv/bin/python benchmarks/bench_containers.py --ar 5 --height 2 --seeds 0 1 2 3 \
        --compare-dynamic
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np
from scipy.stats import t as student

from packing import deposit
from packing.fill import container_fill
from pipeline.scenario_files import load_scenario

# The paper's model (mean ± sd over 10 repeats) and Freeman et al. 2019 (measured, about).
PAPER = {10: (0.286, 0.0052), 25: (0.148, 0.0026)}
FREEMAN = {10: 0.37, 25: 0.18}


def container_scenario(aspect: int, height_lengths: float, seed: int, dynamic: bool):
    """The paper's container for rods of ``aspect`` (built in for 10 and 25 at 4 L high;
    otherwise the AR-10 scenario's rods lengthened or shortened, radius L)."""
    if aspect in PAPER and height_lengths == 4:
        scenario = load_scenario(f"container-ar{aspect}")
    else:
        base = load_scenario("container-ar10")
        chip = dataclasses.replace(base.chip, length_mm=aspect * base.chip.thickness_mm)
        length = chip.length_mm
        scenario = dataclasses.replace(
            base,
            name=f"container-ar{aspect}-h{height_lengths:g}",
            chip=chip,
            container=dataclasses.replace(
                base.container, radius_mm=length, height_mm=height_lengths * length
            ),
            deposition=dataclasses.replace(base.deposition, chips=100_000),
        )
    settling = dataclasses.replace(scenario.settling, freeze=not dynamic)
    return dataclasses.replace(scenario, seed=seed, settling=settling)


def fill(aspect: int, height_lengths: float, seed: int, dynamic: bool) -> dict:
    """One fill: wall time, rods, the two volume fractions, phi L/D, contacts per rod."""
    scenario = container_scenario(aspect, height_lengths, seed, dynamic)
    start = time.perf_counter()
    stack = deposit(scenario)
    seconds = time.perf_counter() - start
    c = scenario.container
    volumes = np.array([stack.shapes[k].volume_mm3 for k in stack.shape_index])
    result = container_fill(stack.positions, volumes, c.radius_mm, c.height_mm)
    last = stack.batches[-1]
    inside = (
        (np.hypot(last.positions[:, 0], last.positions[:, 1]) <= c.radius_mm)
        & (last.positions[:, 2] >= 0)
        & (last.positions[:, 2] <= c.height_mm)
    )
    contacts = last.contacts
    chips = (contacts.chip_a >= 0) & (contacts.chip_b >= 0)
    pairs = {
        (min(a, b), max(a, b))
        for a, b in zip(contacts.chip_a[chips], contacts.chip_b[chips], strict=True)
        if a != b
    }
    touching = np.zeros(len(inside), dtype=int)
    for a, b in pairs:
        touching[a] += 1
        touching[b] += 1
    chip = scenario.chip
    lower = inside & (last.positions[:, 2] < c.height_mm / 2)
    lower_half = volumes[lower].sum() / (np.pi * c.radius_mm**2 * c.height_mm / 2)
    return dict(
        seconds=seconds,
        poured=result["chips_poured"],
        inside=result["chips_inside"],
        phi=result["volume_fraction"],
        lower_half=float(lower_half),
        phi_l_over_d=result["volume_fraction"] * chip.length_mm / chip.thickness_mm,
        contacts_per_rod=float(touching[inside].mean()) if inside.any() else float("nan"),
        full=result["full"],
    )


def summary(values: list[float]) -> str:
    mean = statistics.mean(values)
    if len(values) < 2:
        return f"{mean:.4f}"
    sd = statistics.stdev(values)
    half = student.ppf(0.975, len(values) - 1) * sd / np.sqrt(len(values))
    return f"{mean:.4f} ± {sd:.4f} (95 % interval {mean - half:.4f} to {mean + half:.4f})"


def report(label: str, rows: list[dict], aspect: int) -> None:
    wall = statistics.median(r["seconds"] for r in rows)
    print(f"{label}: wall time median {wall:.0f} s")
    print(f"{label}: volume fraction {summary([r['phi'] for r in rows])}")
    if label.startswith("AR") and aspect in PAPER:
        mean, sd = PAPER[aspect]
        print(f"  paper's model {mean:.3f} ± {sd:.4f}; Freeman et al. measured ~{FREEMAN[aspect]}")
    print(f"{label}: lower half's volume fraction {summary([r['lower_half'] for r in rows])}")
    print(f"{label}: phi L/D {summary([r['phi_l_over_d'] for r in rows])}")
    print(f"{label}: contacts per rod {summary([r['contacts_per_rod'] for r in rows])}")


def compare(frozen: list[dict], dynamic: list[dict]) -> None:
    for key, name in (("phi", "volume fraction"), ("lower_half", "lower half's fraction")):
        a, b = [r[key] for r in frozen], [r[key] for r in dynamic]
        gap = statistics.mean(a) - statistics.mean(b)
        pooled = np.sqrt((statistics.variance(a) + statistics.variance(b)) / 2)
        verdict = "within" if abs(gap) <= pooled else "NOT within"
        print(f"frozen - dynamic, {name}: {gap:+.4f}, pooled sd {pooled:.4f}: {verdict} the spread")
    ratio = statistics.median(r["seconds"] for r in dynamic) / statistics.median(
        r["seconds"] for r in frozen
    )
    print(f"dynamic fills took {ratio:.1f} times as long (medians)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ar", type=int, nargs="+", default=[10, 25])
    parser.add_argument("--height", type=float, default=4.0, help="container height, in L")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument(
        "--compare-dynamic", action="store_true", help="also fill with every rod dynamic"
    )
    args = parser.parse_args()
    modes = (False, True) if args.compare_dynamic else (False,)
    for aspect in args.ar:
        runs: dict[bool, list[dict]] = {mode: [] for mode in modes}
        for seed in args.seeds:
            for dynamic in modes:
                row = fill(aspect, args.height, seed, dynamic)
                runs[dynamic].append(row)
                print(
                    f"AR {aspect} seed {seed}{' dynamic' if dynamic else ''}: "
                    f"{row['seconds']:.0f} s wall, {row['poured']} rods poured, "
                    f"{row['inside']} inside, full {row['full']}, volume fraction "
                    f"{row['phi']:.4f} (lower half {row['lower_half']:.4f}), "
                    f"phi L/D {row['phi_l_over_d']:.2f}, "
                    f"{row['contacts_per_rod']:.2f} contacts per rod",
                    flush=True,
                )
        report(f"AR {aspect}", runs[False], aspect)
        if args.compare_dynamic:
            report(f"AR {aspect} dynamic", runs[True], aspect)
            if len(args.seeds) > 1:
                compare(runs[False], runs[True])


if __name__ == "__main__":
    main()

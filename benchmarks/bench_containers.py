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

Every finished fill is cached as one JSON file in ``benchmarks/results/containers/``,
named by aspect ratio, height, wake speed, frozen or dynamic, seed and a short hash of the
resolved scenario (so a changed scenario never reuses a stale fill); a rerun skips the
fills already cached, so a long study resumes where it stopped. ``--wake-speed`` (mm/s)
overrides the scenario's ``settling.wake_speed_mm_s``; ``--summary-only`` runs nothing and
prints, from the cache, every fill and per (aspect ratio, height, wake speed) the volume
fraction and phi L/D (mean, sd, 95 % t interval) beside the paper's model, Freeman et al.'s
measurement and the random contact equation (phi L/D = 5.4 ± 0.2, Philipse 1996).

    .venv/bin/python benchmarks/bench_containers.py [--ar 10 25] [--seeds 0 1 2]
    .venv/bin/python benchmarks/bench_containers.py --ar 10 --wake-speed 30 --seeds 0 1 2
    .venv/bin/python benchmarks/bench_containers.py --summary-only [--ar 10]
    .venv/bin/python benchmarks/bench_containers.py --ar 5 --height 2 --seeds 0 1 2 3 \
        --compare-dynamic
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import statistics
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from scipy.stats import t as student

from chipstack.core import scenario_to_dict
from chipstack.core.provenance import code_versions
from chipstack.packing import deposit
from chipstack.packing.fill import container_fill
from chipstack.packing.stage import STAGE as PACKING
from chipstack.pipeline.scenario_files import load_scenario

# The paper's model (mean ± sd over 10 repeats) and Freeman et al. 2019 (measured, about).
PAPER = {10: (0.286, 0.0052), 25: (0.148, 0.0026)}
FREEMAN = {10: 0.37, 25: 0.18}
# The random contact equation for long rods, phi L/D (Philipse 1996).
RANDOM_CONTACT = (5.4, 0.2)
RESULTS = Path(__file__).resolve().parent / "results" / "containers"


def container_scenario(
    aspect: int, height_lengths: float, seed: int, dynamic: bool, wake_speed: float | None = None
):
    """The paper's container for rods of ``aspect`` (built in for 10 and 25 at 4 L high;
    otherwise the AR-10 scenario's rods lengthened or shortened, radius L); ``wake_speed``
    (mm/s) overrides ``settling.wake_speed_mm_s``."""
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
    if wake_speed is not None:
        settling = dataclasses.replace(settling, wake_speed_mm_s=float(wake_speed))
    return dataclasses.replace(scenario, seed=seed, settling=settling)


def scenario_hash(scenario) -> str:
    """A short hash of the scenario sections the packing stage depends on, seed excluded
    (the seed is in the cache file's name): a changed scenario never reuses a cached fill."""
    data = scenario_to_dict(scenario)
    keyed = {k: data[k] for k in PACKING.sections if k != "seed" and k in data}
    text = json.dumps(keyed, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def cache_path(results: Path, aspect, height_lengths, wake, dynamic, seed, digest) -> Path:
    mode = "dynamic" if dynamic else "frozen"
    name = f"ar{aspect}-h{height_lengths:g}-wake{wake:g}-{mode}-seed{seed}-{digest}.json"
    return results / name


def source_commit() -> str:
    """The commit the code came from (``BENCH_SOURCE_COMMIT`` for a snapshot without git)."""
    if os.environ.get("BENCH_SOURCE_COMMIT"):
        return os.environ["BENCH_SOURCE_COMMIT"]
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cached_fill(
    results: Path, aspect: int, height_lengths: float, seed: int, dynamic: bool, wake_speed
) -> dict:
    """One fill from the cache, or filled now and cached (written whole or not at all)."""
    scenario = container_scenario(aspect, height_lengths, seed, dynamic, wake_speed)
    digest = scenario_hash(scenario)
    wake = scenario.settling.wake_speed_mm_s
    path = cache_path(results, aspect, height_lengths, wake, dynamic, seed, digest)
    if path.exists():
        row = json.loads(path.read_text())
        row["cached"] = True
        return row
    row = dict(
        aspect=aspect,
        height_lengths=height_lengths,
        wake_speed_mm_s=wake,
        dynamic=dynamic,
        seed=seed,
        scenario=scenario.name,
        scenario_hash=digest,
        **fill(scenario),
        finished=datetime.now(UTC).isoformat(timespec="seconds"),
        commit=source_commit(),
        versions=code_versions(),
    )
    results.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".json.part")
    partial.write_text(json.dumps(row, indent=1) + "\n")
    os.replace(partial, path)
    row["cached"] = False
    return row


def load_cache(results: Path) -> list[dict]:
    """Every cached fill, each marked ``stale`` when its scenario hash is no longer the
    current scenario's (such fills are listed but left out of the statistics)."""
    rows, current = [], {}
    for path in sorted(results.glob("ar*-seed*.json")):
        row = json.loads(path.read_text())
        key = (row["aspect"], row["height_lengths"], row["wake_speed_mm_s"], row["dynamic"])
        if key not in current:
            current[key] = scenario_hash(container_scenario(*key[:2], 0, key[3], key[2]))
        row["stale"] = row["scenario_hash"] != current[key]
        rows.append(row)
    return rows


def fill(scenario) -> dict:
    """One fill: wall time, rods, the two volume fractions, phi L/D, contacts per rod."""
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
        poured=int(result["chips_poured"]),
        inside=int(result["chips_inside"]),
        phi=float(result["volume_fraction"]),
        lower_half=float(lower_half),
        phi_l_over_d=float(result["volume_fraction"] * chip.length_mm / chip.thickness_mm),
        contacts_per_rod=float(touching[inside].mean()) if inside.any() else float("nan"),
        full=bool(result["full"]),
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


def interval(values: list[float]) -> tuple[float, float, float, float]:
    """Mean, sd and the 95 % Student-t interval of the mean (sd and interval nan for one)."""
    mean = statistics.mean(values)
    if len(values) < 2:
        return mean, float("nan"), float("nan"), float("nan")
    sd = statistics.stdev(values)
    half = student.ppf(0.975, len(values) - 1) * sd / np.sqrt(len(values))
    return mean, sd, mean - half, mean + half


def fill_line(row: dict) -> str:
    return (
        f"AR {row['aspect']} h {row['height_lengths']:g} L wake {row['wake_speed_mm_s']:g} "
        f"seed {row['seed']}{' dynamic' if row['dynamic'] else ''}"
        f"{' (cached)' if row.get('cached') else ''}{' STALE' if row.get('stale') else ''}: "
        f"{row['seconds']:.0f} s wall, {row['poured']} rods poured, "
        f"{row['inside']} inside, full {row['full']}, volume fraction "
        f"{row['phi']:.4f} (lower half {row['lower_half']:.4f}), "
        f"phi L/D {row['phi_l_over_d']:.2f}, "
        f"{row['contacts_per_rod']:.2f} contacts per rod"
    )


def table(rows: list[dict]) -> None:
    """Per (aspect ratio, height, wake speed, frozen or dynamic): the volume fraction and
    phi L/D with 95 % intervals beside the paper's model, Freeman et al. and 5.4 ± 0.2."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        key = (row["aspect"], row["height_lengths"], row["wake_speed_mm_s"], row["dynamic"])
        groups.setdefault(key, []).append(row)
    target, target_sd = RANDOM_CONTACT
    print(
        "\n| AR | height | wake (mm/s) | settled rods | fills (seeds) | volume fraction, mean ± sd "
        "| 95 % interval | paper's PyBullet | Freeman measured | ours - measured "
        f"| phi L/D [95 % interval] (random contact {target} ± {target_sd}) "
        "| contacts per rod | median wall |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (aspect, height, wake, dynamic), group in sorted(groups.items()):
        group.sort(key=lambda r: r["seed"])
        seeds = [r["seed"] for r in group]
        contiguous = seeds == list(range(seeds[0], seeds[-1] + 1))
        if len(seeds) > 1 and contiguous:
            span = f"{seeds[0]}-{seeds[-1]}"
        else:
            span = ", ".join(str(seed) for seed in seeds)
        phi, sd, lo, hi = interval([r["phi"] for r in group])
        pld, _, pld_lo, pld_hi = interval([r["phi_l_over_d"] for r in group])
        contacts, contacts_sd, _, _ = interval([r["contacts_per_rod"] for r in group])
        wall = statistics.median(r["seconds"] for r in group)
        paper = measured = gap = "-"
        if aspect in PAPER and height == 4:
            paper = f"{100 * PAPER[aspect][0]:.1f} % ± {100 * PAPER[aspect][1]:.2f}"
            measured = f"about {100 * FREEMAN[aspect]:.0f} %"
            theirs = PAPER[aspect][0] - FREEMAN[aspect]
            gap = f"{100 * (phi - FREEMAN[aspect]):+.1f} points (paper {100 * theirs:+.1f})"
        print(
            f"| {aspect} | {height:g} L | {wake:g} "
            f"| {'dynamic' if dynamic else 'frozen'} | {len(group)} ({span}) "
            f"| {100 * phi:.1f} % ± {100 * sd:.2f} | {100 * lo:.1f} to {100 * hi:.1f} % "
            f"| {paper} | {measured} | {gap} "
            f"| {pld:.2f} [{pld_lo:.2f} to {pld_hi:.2f}] ({pld - target:+.2f}) "
            f"| {contacts:.2f} ± {contacts_sd:.2f} | {wall:.0f} s |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ar", type=int, nargs="+", default=None, help="aspect ratios (10 25)")
    parser.add_argument(
        "--height", type=float, default=None, help="container height, in L (default 4)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument(
        "--wake-speed",
        type=float,
        default=None,
        help="settling.wake_speed_mm_s for the fills, mm/s (default: the scenario's)",
    )
    parser.add_argument(
        "--compare-dynamic", action="store_true", help="also fill with every rod dynamic"
    )
    parser.add_argument(
        "--summary-only",
        action="store_true",
        help="run nothing: print the cached fills and their tables (--ar, --height, "
        "--wake-speed filter them)",
    )
    parser.add_argument(
        "--results", type=Path, default=RESULTS, help="cache folder (one JSON per fill)"
    )
    args = parser.parse_args()
    if args.summary_only:
        rows = [
            r
            for r in load_cache(args.results)
            if (args.ar is None or r["aspect"] in args.ar)
            and (args.height is None or r["height_lengths"] == args.height)
            and (args.wake_speed is None or r["wake_speed_mm_s"] == args.wake_speed)
        ]
        if not rows:
            print(f"no cached fills in {args.results}")
            return
        for row in sorted(rows, key=lambda r: (r["aspect"], r["wake_speed_mm_s"], r["seed"])):
            print(fill_line(row))
        stale = [r for r in rows if r["stale"]]
        if stale:
            print(f"{len(stale)} cached fills of a changed scenario (STALE) left out below")
        table([r for r in rows if not r["stale"]])
        return
    height = 4.0 if args.height is None else args.height
    modes = (False, True) if args.compare_dynamic else (False,)
    done: list[dict] = []
    for aspect in args.ar or [10, 25]:
        runs: dict[bool, list[dict]] = {mode: [] for mode in modes}
        for seed in args.seeds:
            for dynamic in modes:
                row = cached_fill(args.results, aspect, height, seed, dynamic, args.wake_speed)
                runs[dynamic].append(row)
                done.append(row)
                print(fill_line(row), flush=True)
        report(f"AR {aspect}", runs[False], aspect)
        if args.compare_dynamic:
            report(f"AR {aspect} dynamic", runs[True], aspect)
            if len(args.seeds) > 1:
                compare(runs[False], runs[True])
    table(done)


if __name__ == "__main__":
    main()

"""Does a drop's outcome depend on the integration step? The single-chip drop
(``single-chip-drop``, its release tilt) simulated at several ``physics.time_step_s``,
rigid floor and compliant floors, and the observables the diagnosis compares printed
with their bootstrap sd, so that a difference between steps can be read against the
sampling noise of the drops themselves.

Each setting is one ``packing.drop.simulate_drops`` call (all drops in one world, the
same release draws at every step and strength: common random numbers), run as a task
on ``--workers`` local Dask workers. Prints, per step and compliance: the quartiles and
90th percentile of the distance from the release point (mm), the sd of the final yaw
(deg), each as value (bootstrap sd), and the wall time of the setting.

Usage: ``python benchmarks/bench_drop_time_step.py [--height 200] [--drops 120]
[--steps 5e-4 2.5e-4 1e-4 5e-5] [--compliances 0 0.05 0.1 0.6 0.7 0.75] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from chipstack.packing.drop import DropProtocol, simulate_drops
from chipstack.pipeline.execution import Executor
from chipstack.pipeline.scenario_files import load_scenario

BOOTSTRAP = 400


def _timed(scenario, protocol, n, strengths, seed):
    start = time.perf_counter()
    sample = simulate_drops(scenario, protocol, n, strengths, seed)
    return sample, time.perf_counter() - start


def _summary(sample, rng) -> list[tuple[float, float]]:
    """(value, bootstrap sd) of r q25, q50, q75, q90 and the yaw sd."""
    r = np.linalg.norm(sample.positions, axis=1)
    yaw = sample.yaw_deg

    def stats(index):
        return [*np.quantile(r[index], [0.25, 0.5, 0.75, 0.9]), yaw[index].std()]

    point = stats(np.arange(len(r)))
    boot = np.array([stats(rng.integers(0, len(r), len(r))) for _ in range(BOOTSTRAP)])
    return list(zip(point, boot.std(axis=0), strict=True))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--height", type=float, default=200.0)
    parser.add_argument("--drops", type=int, default=120)
    parser.add_argument("--steps", type=float, nargs="+", default=[5e-4, 2.5e-4, 1e-4, 5e-5])
    parser.add_argument(
        "--compliances", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.6, 0.7, 0.75]
    )
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    base = load_scenario("single-chip-drop")
    protocol = DropProtocol(height_mm=args.height, tilt_deg=base.drop.tilt_deg)
    settings = [(dt, c) for dt in args.steps for c in args.compliances]
    calls = [
        dict(
            scenario=replace(base, physics=replace(base.physics, time_step_s=dt)),
            protocol=protocol,
            n=args.drops,
            strengths={"compliant_floor": c} if c > 0 else {},
            seed=args.seed,
        )
        for dt, c in settings
    ]
    with Executor(workers=args.workers) as executor:
        results = executor.map(_timed, calls)
    rng = np.random.default_rng(0)
    print(
        f"single-chip-drop from {args.height:g} mm, {args.drops} drops a setting, release "
        f"tilt {base.drop.tilt_deg:g} deg, seed {args.seed}; value (bootstrap sd)\n"
    )
    columns = ["r q25", "r q50", "r q75", "r q90", "yaw sd (deg)", "wall (s)"]
    print("| step (ms) | floor compliance (mm/N) | " + " | ".join(columns) + " |")
    print("|---|---|---|---|---|---|---|---|")
    for (dt, c), (sample, seconds) in zip(settings, results, strict=True):
        cells = " | ".join(f"{v:.2f} ({s:.2f})" for v, s in _summary(sample, rng))
        print(f"| {1e3 * dt:g} | {c:g} | {cells} | {seconds:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Kill-and-resume campaign: real runs killed with SIGKILL at random moments, resumed
(killed again, sometimes), and compared byte for byte with an uninterrupted run.

    python benchmarks/bench_resume.py [--kills 10] [--seed 0] [--scenario FILE]

Prints, per attempt, when the kill fell (the journal's state at that moment), how many
starts the run took, and whether every file matched; then the totals and the time an
uninterrupted run takes beside the total time of the interrupted ones. The share of runs
that matched is recorded as data (``pipeline.measured.record``, area ``reliability``;
``--no-record`` for a trial) and shown in docs/measured.md after ``make docs``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SCENARIO = """
name = "campaign"
seed = 5
[chip]
length_mm = 20.0
width_mm = 10.0
thickness_mm = 2.0
[deposition]
chips = 60
batch_size = 10
target_size_mm = 70.0
release_height_mm = [40.0, 100.0]
"""
ARGS = ["--to", "mesh", "--formats", "vtu,inp", "--quiet"]


def _command(scenario: Path, out: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "chipstack.pipeline",
        "run",
        str(scenario),
        "--out",
        str(out),
        *ARGS,
    ]


def _files(run: Path) -> dict[str, bytes]:
    return {
        p.relative_to(run).as_posix(): p.read_bytes()
        for p in sorted(run.rglob("*"))
        if p.is_file() and p.name != "manifest.json"
    }


def _where(partial: Path) -> str:
    try:
        journal = json.loads((partial / "manifest.json").read_text())
    except (OSError, ValueError):
        return "before the journal"
    stages = journal.get("stages", {})
    done = [s for s, e in stages.items() if e.get("status") == "complete"]
    if done:
        return f"stages done: {', '.join(done)}"
    return f"depositing, batches done: {stages.get('packing', {}).get('batches_completed', 0)}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenario", type=Path, default=None)
    parser.add_argument("--no-record", action="store_true", help="do not record the figure")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    root = Path(tempfile.mkdtemp(prefix="chipstack-resume-"))
    scenario = args.scenario or root / "campaign.toml"
    if args.scenario is None:
        scenario.write_text(SCENARIO)
    reference = root / "reference"
    start = time.perf_counter()
    subprocess.run(_command(scenario, reference), check=True)
    uninterrupted = time.perf_counter() - start
    print(f"uninterrupted run: {uninterrupted:.1f} s")
    matched = 0
    for attempt in range(args.kills):
        out = root / f"run{attempt}"
        starts, kills, spent, where = 0, [], 0.0, []
        while True:
            starts += 1
            began = time.perf_counter()
            process = subprocess.Popen(
                _command(scenario, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
            )
            # Kill at a uniform moment of the uninterrupted run's length, twice at most.
            delay = rng.uniform(0.5, uninterrupted) if len(kills) < 2 else None
            try:
                process.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                where.append(_where(root / f".{out.name}.partial"))
                os.kill(process.pid, signal.SIGKILL)
                process.wait()
                kills.append(round(delay, 2))
            spent += time.perf_counter() - began
            if process.returncode == 0:
                break
            if process.returncode != -signal.SIGKILL:
                raise SystemExit(f"attempt {attempt}: run failed with {process.returncode}")
        same = _files(out) == _files(reference)
        matched += same
        print(
            f"attempt {attempt}: killed at {kills} s ({'; '.join(where) or 'finished first'}), "
            f"{starts} starts, {spent:.1f} s in all, files identical: {same}"
        )
        shutil.rmtree(out)
    print(f"{matched} of {args.kills} interrupted runs matched the uninterrupted one bit for bit")
    shutil.rmtree(root)
    if not args.no_record and args.kills:
        from chipstack.pipeline.measured import record

        record(
            "reliability",
            "killed and resumed runs identical to an uninterrupted run",
            round(100 * matched / args.kills, 1),
            "%",
            target="== 100",
            command="python " + " ".join(["benchmarks/bench_resume.py", *sys.argv[1:]]),
            note=f"{matched} of {args.kills} runs, each killed up to twice with SIGKILL",
        )


if __name__ == "__main__":
    main()

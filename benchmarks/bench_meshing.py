"""Meshing speed: the voxel mesh and the conformal mesh of the 270-chip reference stack.

Deposits the reference stack (seed 0), then times ``voxel_mesh`` at 0.5 mm (target
<= 10 s) and tries ``conformal_mesh`` at 1.5 mm (target <= 60 s, peak memory <= 4 GB),
printing its failure if it fails; each in a fresh process so peak memory is its own.

    .venv/bin/python benchmarks/bench_meshing.py
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import json, pickle, resource, sys, time
from meshing import conformal_mesh, voxel_mesh, MeshingError
arrangement = pickle.load(open(sys.argv[1], "rb"))
kind = sys.argv[2]
start = time.perf_counter()
result = {"kind": kind}
try:
    if kind == "voxel":
        mesh = voxel_mesh(arrangement, 0.5)
    else:
        mesh = conformal_mesh(arrangement, 1.5)
    result.update(elements=mesh.n_elements, nodes=len(mesh.points),
                  quality_min=float(mesh.quality.min()))
except MeshingError as exc:
    result["error"] = str(exc)
result["seconds"] = time.perf_counter() - start
result["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(result))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from geometry import arrangements_from_stack
    from packing import deposit, scenario_from_dict

    stack = deposit(scenario_from_dict({"seed": args.seed}))
    arrangement = arrangements_from_stack(stack)[-1]
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "stack.pkl"
        path.write_bytes(pickle.dumps(arrangement))
        for kind in ("voxel", "conformal"):
            start = time.perf_counter()
            out = subprocess.run(
                [sys.executable, "-c", CHILD, str(path), kind], capture_output=True, text=True
            )
            if out.returncode != 0:
                print(f"{kind}: crashed after {time.perf_counter() - start:.1f} s")
                print(out.stderr[-2000:])
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            if "error" in r:
                print(
                    f"{kind}: FAILED after {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB: "
                    f"{r['error']}"
                )
            else:
                print(
                    f"{kind}: {r['elements']:,} elements, {r['nodes']:,} nodes, quality min "
                    f"{r['quality_min']:.3f}, {r['seconds']:.1f} s, peak {r['peak_mb']:.0f} MB"
                )
    print(
        f"(this process: peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB)"
    )


if __name__ == "__main__":
    main()

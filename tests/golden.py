"""Hashes of a run's result files, for the byte-identity check of refactors.

Everything a run computes is hashed; what records when or how fast it ran (the
manifest, wall times in ``descriptors.json`` and the mesh checks), the resolved
``scenario.toml`` (the input, which gains a line with every new scenario key) and the PNG
figures (pictures of the results, rendered by a library whose version moves) are not.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

SKIPPED = ("manifest.json", "scenario.toml")
TIMING_KEYS = ("wall_time_s", "mesh_time_s", "time_s")
# Keys that new checks added to a file after the hashes were recorded; everything else in
# the file must still match.
ADDED_KEYS = ("chips_in_pieces", "chips_in_pieces_count", "bounds_mm")


def _without_timings(data):
    if isinstance(data, dict):
        return {
            k: _without_timings(v)
            for k, v in data.items()
            if not any(k.endswith(t) or k == t for t in TIMING_KEYS) and k not in ADDED_KEYS
        }
    if isinstance(data, list):
        return [_without_timings(v) for v in data]
    return data


def result_hashes(run: Path) -> dict[str, str]:
    """SHA-256 of every result file of a run directory, by path relative to it."""
    hashes = {}
    for path in sorted(Path(run).rglob("*")):
        name = path.relative_to(run).as_posix()
        if not path.is_file() or path.suffix == ".png" or name in SKIPPED:
            continue
        data = path.read_bytes()
        if path.suffix == ".json":
            data = json.dumps(_without_timings(json.loads(data)), sort_keys=True).encode()
        hashes[name] = hashlib.sha256(data).hexdigest()
    return hashes

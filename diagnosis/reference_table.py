"""The reference table of the amortised model choice: drops simulated once per model,
strength and release, kept on disk, and cut into datasets of any design that shares a
condition.

A *pool* is one setting of one model (no effect, or one effect at one strength, at one
release tilt) simulated ``pool_drops`` times at one release condition, without
measurement noise. Pool j of a model has the same strength (and, with the release tilt a
nuisance, the same tilt) in every condition, drawn from a scrambled Halton sequence over
the effect's prior, so that the pools of a model cover its prior evenly and a table grows
by adding pools without moving the ones it has. The datasets of a design are cut from
the pools (pool j's drops k n to (k + 1) n in every condition), with the design's own
measurement noise drawn per dataset; datasets of one pool share a strength, so the
cross-validation keeps them together.

Pools are stored by condition (height, yaw, tilt rule), model and the simulation's key
(the scenario's chip, physics and settling, and the code that simulates), so a design
that shares a condition with an earlier one reuses its drops. A pool's drop k depends
on its seed and k alone (``simulate_drops``), so the first P drops of a longer stored
pool are exactly a pool of P drops: a table stored with more drops per pool serves any
design that needs fewer. The store is given by the
caller (``pipeline diagnose`` keeps it in a cache directory); :class:`MemoryStore` keeps
it in memory.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
from scipy.stats import qmc

from chipstack.core.scenario_data import scenario_to_dict
from chipstack.diagnosis.model import Experiment
from chipstack.packing.drop import DropProtocol, simulate_drops
from chipstack.packing.effects import EFFECTS

__all__ = [
    "NO_EFFECT",
    "MemoryStore",
    "ReferenceTable",
    "TableStore",
    "code_version",
    "pool_drops_for",
    "simulate_pool",
]

log = logging.getLogger(__name__)

NO_EFFECT = "no effect"
# Bumped when the table's layout or its draws change (a new key: old pools are not reused).
TABLE_VERSION = 1
# The version of what a drop simulation (``packing``) returns: raised by hand when a change
# changes a simulated drop (a new key: old pools are not reused). The test of
# :func:`fingerprint_drops` fails until it is; a refactor that changes no drop keeps it,
# and with it every stored pool. Its first value is the digest of ``packing/*.py`` that
# keyed the pools before this version did (the pools under benchmarks/cache were made
# with that code).
SIMULATION_VERSION = "2b44656df5b9faec"
# The release tilt range drawn when it is a nuisance (``release_tilt = "fitted"``), deg.
NUISANCE_TILT_DEG = (0.0, 20.0)
# Drops per pool (per condition). The table's cost is proportional; the cross-validated
# accuracy on the study's design (3 x 50 drops) does not depend on it, while it grows with
# the pools per effect (strengths covered): benchmarks/bench_table_size.py. So pools are
# kept short (two datasets of 50 drops) and the table grows by pools.
DEFAULT_POOL_DROPS = 100
_SEED_BASE = 300_000_000  # apart from the diagnosis's (seed * 1000 + ...) and synth's (1e7)


class TableStore(Protocol):
    """Where pools and trained models are kept: named blobs of bytes."""

    def load(self, name: str) -> bytes | None: ...

    def save(self, name: str, blob: bytes) -> None: ...


class MemoryStore:
    """A :class:`TableStore` in memory (tests, one-off diagnoses)."""

    def __init__(self) -> None:
        self.blobs: dict[str, bytes] = {}

    def load(self, name: str) -> bytes | None:
        return self.blobs.get(name)

    def save(self, name: str, blob: bytes) -> None:
        self.blobs[name] = blob


def pool_drops_for(drops: dict[str, int], at_least: int | None = None) -> int:
    """Drops per pool for a design with ``drops`` per condition: the default (or
    ``at_least``), and never fewer than two datasets of the design (the calibrated
    predictive check cuts two disjoint ones from every pool)."""
    return max(at_least or DEFAULT_POOL_DROPS, 2 * max(drops.values()))


def code_version() -> str:
    """The version of what the table's pools hold: :data:`SIMULATION_VERSION` (what a drop
    simulation returns) and :data:`TABLE_VERSION` (the layout). A change to either gives
    new keys, so no stale pool is reused; a change to the code that leaves every drop as
    it was (a refactor) keeps the keys and the stored pools."""
    if TABLE_VERSION == 1:  # the layout the first pools were stored with: no suffix
        return SIMULATION_VERSION
    return f"{SIMULATION_VERSION}-table{TABLE_VERSION}"


def fingerprint_drops(scenario) -> dict[str, list]:
    """Three drops of every effect a drop experiment can have, and of none, at one release
    condition of ``scenario`` (the tests': the built-in ``single-chip-drop``): what
    :data:`SIMULATION_VERSION` names. ``tests/data/drop_fingerprint.json`` holds them for
    the version; a test simulates them again and fails when they differ, until the version
    is raised and the file written again (:func:`write_fingerprint`)."""
    protocol = DropProtocol(height_mm=500.0, yaw_deg=30.0)
    out = {}
    for model in [NO_EFFECT, *sorted(e for e in EFFECTS if "drop" in EFFECTS.get(e).kinds)]:
        strengths = {}
        if model != NO_EFFECT:
            lo, hi = EFFECTS.get(model).prior
            strengths = {model: lo + 0.7 * (hi - lo)}
        out[model] = simulate_pool(scenario, protocol, 3, strengths, seed=11).tolist()
    return out


def write_fingerprint(scenario, path: Path | None = None) -> Path:
    """Write :func:`fingerprint_drops` of ``scenario`` with :data:`SIMULATION_VERSION` (the
    tests' file by default): after raising the version for a change that changes drops."""
    path = (
        path or Path(__file__).resolve().parent.parent / "tests" / "data" / "drop_fingerprint.json"
    )
    text = json.dumps({"version": code_version(), "drops": fingerprint_drops(scenario)}, indent=1)
    path.write_text(text + "\n")
    return path


# The scenario's sections a drop simulation reads (``packing.drop.simulate_drops``: the
# chip or the mix and the seed its shape is drawn with, the physics, the settling rule,
# the drop settings); the others (mesh, solve, geometry, ...) change no drop, so a key
# added to them keeps every stored pool.
SIMULATED_SECTIONS = ("seed", "chip", "mix", "physics", "settling", "drop")


def simulation_key(scenario) -> str:
    """A digest of what a drop simulation of ``scenario`` depends on besides its call:
    the scenario's :data:`SIMULATED_SECTIONS` and :func:`code_version`."""
    everything = scenario_to_dict(scenario)
    settings = {name: everything.get(name) for name in SIMULATED_SECTIONS}
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(f"{text}|{code_version()}".encode()).hexdigest()[:16]


def simulate_pool(scenario, protocol: DropProtocol, n: int, strengths: dict, seed: int):
    """``n`` noise-free drops as a (n, 4) float32 array: x, y (mm), yaw, tilt (deg)."""
    sample = simulate_drops(scenario, protocol, n, strengths, seed)
    return np.column_stack(
        [sample.positions, sample.yaw_deg[:, None], sample.tilt_deg[:, None]]
    ).astype(np.float32)


@dataclass(frozen=True)
class PoolSetting:
    """Pool ``index`` of ``model``: its strength (nan for no effect) and tilt (deg)."""

    model: str
    index: int
    strength: float
    tilt_deg: float


class ReferenceTable:
    """The pools of one experiment's conditions, for a set of models, in ``store``.

    ``release_tilt`` "known": every pool released at the condition's own tilt; "fitted":
    the tilt is a nuisance, drawn per pool over :data:`NUISANCE_TILT_DEG`."""

    def __init__(
        self,
        experiment: Experiment,
        models: list[str],
        store: TableStore,
        pool_drops: int = DEFAULT_POOL_DROPS,
    ) -> None:
        self.x = experiment
        self.models = list(models)
        self.store = store
        self.release_tilt = experiment.settings.release_tilt
        self.pool_drops = int(pool_drops)
        self.simulation_key = simulation_key(experiment.scenario)
        # (condition, model) -> (J, pool_drops, 4): the first pool_drops drops of each pool
        self.pools: dict[tuple[str, str], np.ndarray] = {}
        # The same as stored, (J, P', 4) with P' >= pool_drops: a longer stored pool is
        # grown at its own length, so that the store keeps whole pools.
        self._whole: dict[tuple[str, str], np.ndarray] = {}

    # -- settings of pools ----------------------------------------------------------------
    def settings(self, model: str, count: int) -> list[PoolSetting]:
        """The first ``count`` pools of ``model`` (the same whatever ``count``)."""
        seed = zlib.crc32(model.encode())
        unit = qmc.Halton(d=2, scramble=True, seed=seed).random(count) if count else []
        out = []
        for j in range(count):
            strength = math.nan
            if model != NO_EFFECT:
                lo, hi = EFFECTS.get(model).prior
                strength = float(lo + (hi - lo) * unit[j][0])
            tilt = math.nan
            if self.release_tilt == "fitted":
                lo_t, hi_t = NUISANCE_TILT_DEG
                tilt = float(lo_t + (hi_t - lo_t) * unit[j][1])
            out.append(PoolSetting(model, j, strength, tilt))
        return out

    def _protocol(self, condition: str, setting: PoolSetting) -> DropProtocol:
        protocol = self.x.condition(condition).protocol
        if math.isnan(setting.tilt_deg):
            return protocol
        return replace(protocol, tilt_deg=setting.tilt_deg)

    def _name(self, condition: str, model: str) -> str:
        p = self.x.condition(condition).protocol
        tilt = "nuisance" if self.release_tilt == "fitted" else f"{p.tilt_deg:g}"
        return (
            f"pools-{self.simulation_key}-h{p.height_mm:g}-yaw{p.yaw_deg:g}-tilt{tilt}"
            f"-{model.replace(' ', '_')}.npy"
        )

    def _seed(self, condition: str, setting: PoolSetting) -> int:
        p = self._protocol(condition, setting)
        text = f"{setting.model}|{setting.index}|{p.height_mm:g}|{p.yaw_deg:g}"
        return _SEED_BASE + zlib.crc32(text.encode()) % 100_000_000

    def call(self, condition: str, setting: PoolSetting) -> dict:
        """The keyword arguments of :func:`simulate_pool` for one pool at one condition
        (as many drops as the stored pools of its model hold, if they hold more)."""
        return dict(
            scenario=self.x.scenario,
            protocol=self._protocol(condition, setting),
            n=max(self.pool_drops, self._stored_drops(condition, setting.model)),
            strengths={} if setting.model == NO_EFFECT else {setting.model: setting.strength},
            seed=self._seed(condition, setting),
        )

    # -- simulating -------------------------------------------------------------------------
    def load(self) -> None:
        """Read every stored pool of the experiment's conditions and models (the first
        ``pool_drops`` drops of each; pools stored shorter than that are simulated
        again)."""
        for c in self.x.conditions:
            for model in self.models:
                blob = self.store.load(self._name(c.name, model))
                if blob is None:
                    continue
                stored = _from_bytes(blob)
                if stored.shape[1] < self.pool_drops:
                    log.info(
                        "%s: stored pools hold %d drops, %d needed: simulated again",
                        self._name(c.name, model),
                        stored.shape[1],
                        self.pool_drops,
                    )
                    continue
                self._keep((c.name, model), stored)

    def _stored_drops(self, condition: str, model: str) -> int:
        """Drops per pool of the model's stored pools at the condition (0: none stored)."""
        whole = self._whole.get((condition, model))
        return 0 if whole is None else whole.shape[1]

    def _keep(self, key: tuple[str, str], whole: np.ndarray) -> None:
        self._whole[key] = whole
        self.pools[key] = whole[:, : self.pool_drops]

    def count(self, model: str) -> int:
        """Pools of ``model`` simulated in every condition."""
        return min(len(self.pools.get((c.name, model), ())) for c in self.x.conditions)

    def ensure(
        self,
        counts: dict[str, int],
        run_many: Callable[[Callable, list[dict]], list],
        progress: Callable[[str], None],
    ) -> int:
        """Simulate the pools missing for ``counts`` (model -> pools) in every condition;
        return the number of drops simulated."""
        wanted = []
        for model, count in counts.items():
            for setting in self.settings(model, count):
                for c in self.x.conditions:
                    have = len(self.pools.get((c.name, model), ()))
                    if setting.index >= have:
                        wanted.append((c.name, setting))
        if not wanted:
            return 0
        calls = {(c, s.model, s.index): self.call(c, s) for c, s in wanted}
        total = sum(call["n"] for call in calls.values())
        progress(f"reference table: simulating {len(wanted)} pools, {total} drops")
        done = 0
        # One batch per model: each is stored when it is done, so a killed build keeps
        # every finished model's pools and resumes from there.
        for model in dict.fromkeys(s.model for _, s in wanted):
            mine = [(c, s) for c, s in wanted if s.model == model]
            results = run_many(simulate_pool, [calls[c, s.model, s.index] for c, s in mine])
            for (c, _setting), result in sorted(
                zip(mine, results, strict=True), key=lambda item: item[0][1].index
            ):
                have = self._whole.get((c, model))
                block = np.asarray(result, dtype=np.float32)[None]
                self._keep((c, model), block if have is None else np.concatenate([have, block]))
            for c in dict.fromkeys(c for c, _ in mine):
                self.store.save(self._name(c, model), _to_bytes(self._whole[c, model]))
            done += len(mine)
            progress(f"reference table: {done} of {len(wanted)} pools ({model} done)")
        return total

    # -- datasets -----------------------------------------------------------------------------
    def datasets(
        self,
        counts: dict[str, int],
        drops: dict[str, int],
        rng: np.random.Generator,
        per_pool_at_least: int = 4,
    ) -> list[TableDataset]:
        """Datasets of the design (``drops`` per condition) cut from the first
        ``counts[model]`` pools of each model, measurement noise added: the pool's
        disjoint slices, then random subsets of it up to ``per_pool_at_least``."""
        conditions = [c.name for c in self.x.conditions]
        per_pool = max(1, min(self.pool_drops // drops[c] for c in conditions))
        out = []
        for model, count in counts.items():
            for s in self.settings(model, count):
                for k in range(max(per_pool, per_pool_at_least)):
                    data = {}
                    for c in conditions:
                        pool = self.pools[c, model][s.index]
                        n = drops[c]
                        if k < per_pool:
                            index = np.arange(k * n, (k + 1) * n)
                        else:  # a small pool: further datasets are random subsets of it
                            index = np.sort(rng.choice(len(pool), size=n, replace=False))
                        data[c] = self.noisy(pool[index], rng)
                    out.append(TableDataset(s, data, k if k < per_pool else -1))
        return out

    def noisy(self, drops: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The experiment's measurement noise on noise-free drops (as ``synth`` adds it)."""
        n = len(drops)
        out = drops.astype(float)
        out[:, :2] += rng.normal(0.0, self.x.position_sd_mm, size=(n, 2))
        out[:, 2] += rng.normal(0.0, self.x.angle_sd_deg, size=n)
        tilt = np.abs(out[:, 3] + rng.normal(0.0, self.x.angle_sd_deg, size=n))
        out[:, 3] = np.minimum(tilt, 180.0 - tilt)
        return out


@dataclass(frozen=True)
class TableDataset:
    """One simulated dataset of the design: its pool's setting, (n, 4) drops per
    condition (x, y mm; yaw, tilt deg) and which slice of the pool they are."""

    setting: PoolSetting
    drops: dict[str, np.ndarray]
    part: int = -1  # which disjoint slice of its pool (-1: a random subset)


def _to_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def _from_bytes(blob: bytes) -> np.ndarray:
    return np.load(io.BytesIO(blob), allow_pickle=False)

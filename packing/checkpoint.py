"""The deposition's state between batches, and a settled stack, as plain arrays.

A run killed during deposition resumes from the state after its last completed batch.
For the resumed run to end bit for bit where an uninterrupted one would, every run goes
through the same door: after each batch the state is turned into arrays, read back from
them, and the next batch starts in a new physics world built from what was read. A
resumed run reads the same arrays from a file (``numpy.savez``: float64 exact, shapes as
JSON whose floats round-trip exactly).

The arrays are a flat ``{name: ndarray}`` mapping, so they go into an ``.npz`` file with
``allow_pickle=False``.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.core.errors import InputError, brief
from chipstack.core.stack import BatchResult, Stack
from chipstack.packing.shapes import ChipShape, shape_from_record, shape_record
from chipstack.packing.world import ContactRecord

__all__ = [
    "load_stack",
    "DepositionState",
    "state_to_arrays",
    "state_from_arrays",
    "stack_to_arrays",
    "stack_from_arrays",
    "STATE_SCHEMA",
    "STACK_SCHEMA",
]

STATE_SCHEMA = "chipstack.deposition-state/1"
STACK_SCHEMA = "chipstack.stack/1"
_CONTACT_FIELDS = ("chip_a", "chip_b", "point_a", "point_b", "normal", "distance")
_RESULT_NUMBERS = (
    "batch",
    "sim_time_s",
    "wall_time_s",
    "steps",
    "settled",
    "wakes",
    "max_floor_penetration_mm",
    "max_chip_penetration_mm",
    "outside_target",
)


@dataclass(frozen=True)
class DepositionState:
    """Everything the deposition carries from one batch to the next.

    ``pool``: every shape in use (chips' shapes, and the builder's cache of shapes that
    do not vary between chips); the other fields refer to shapes by index into it, so
    shared shapes stay shared after a round trip.
    """

    batches_done: int
    time_s: float  # simulated time so far (s)
    rng_state: dict[str, Any]  # numpy bit generator state
    pool: tuple[ChipShape, ...]
    chip_shape: np.ndarray  # (n,) index into pool
    chip_batch: np.ndarray  # (n,) 1-based batch of each chip
    positions: np.ndarray  # (n, 3) mm
    quaternions: np.ndarray  # (n, 4) x, y, z, w
    results: tuple[BatchResult, ...]  # the batches recorded so far
    warnings: tuple[str, ...]
    # draw_shapes' cache: (chip spec index, size factor, pool index)
    cache: tuple[tuple[int, float, int], ...] = ()
    # effects' reshaped chips: (pool index of the plain shape, pool index of the reshaped)
    reshaped: tuple[tuple[int, int], ...] = ()
    floor_reference_mass_g: float | None = None
    full: bool = False  # a container reached its rim
    extra: dict[str, Any] = field(default_factory=dict)


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python number JSON can hold (exactly)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not a plain number")


def _text(value: Any) -> np.ndarray:
    return np.array(json.dumps(value, default=_plain))


def _json(arrays: dict[str, np.ndarray], name: str, where: str) -> Any:
    try:
        return json.loads(str(arrays[name][()]))
    except (KeyError, ValueError) as exc:
        raise InputError(f"{where}: unreadable field {name!r} ({exc})") from None


def _meta(arrays, schema: str, what: str, where: str) -> dict[str, Any]:
    """The record's ``meta`` table, refused unless it carries ``schema``."""
    meta = _json(arrays, "meta", where)
    if not isinstance(meta, dict) or meta.get("schema") != schema:
        raise InputError(f"{where}: not a {what} ({schema})")
    return meta


def _results_to_arrays(
    results: tuple[BatchResult, ...], timings: bool = True
) -> dict[str, np.ndarray]:
    """``timings``: keep the wall times (a state file); a result file holds only results,
    so that identical runs write identical files."""
    arrays: dict[str, np.ndarray] = {}
    numbers = []
    for k, r in enumerate(results):
        arrays[f"result{k}_positions"] = np.asarray(r.positions, dtype=float)
        arrays[f"result{k}_quaternions"] = np.asarray(r.quaternions, dtype=float)
        for name in _CONTACT_FIELDS:
            arrays[f"result{k}_contact_{name}"] = np.asarray(getattr(r.contacts, name))
        numbers.append({n: getattr(r, n) for n in _RESULT_NUMBERS if timings or n != "wall_time_s"})
    arrays["results"] = _text(numbers)
    return arrays


def _results_from_arrays(arrays, where: str) -> tuple[BatchResult, ...]:
    results = []
    for k, numbers in enumerate(_json(arrays, "results", where)):
        try:
            contacts = ContactRecord(
                **{name: arrays[f"result{k}_contact_{name}"] for name in _CONTACT_FIELDS}
            )
            results.append(
                BatchResult(
                    positions=arrays[f"result{k}_positions"],
                    quaternions=arrays[f"result{k}_quaternions"],
                    contacts=contacts,
                    **{n: numbers[n] for n in _RESULT_NUMBERS if n != "wall_time_s"},
                    wall_time_s=float(numbers.get("wall_time_s", "nan")),
                )
            )
        except (KeyError, TypeError) as exc:
            raise InputError(f"{where}: batch record {k} is incomplete ({exc})") from None
    return tuple(results)


def _shapes_from(arrays, name: str, where: str) -> tuple[ChipShape, ...]:
    records = _json(arrays, name, where)
    if not isinstance(records, list):
        raise InputError(f"{where}: {name} is not a list of shapes")
    return tuple(shape_from_record(r, f"{where} shape {k}") for k, r in enumerate(records))


def state_to_arrays(state: DepositionState) -> dict[str, np.ndarray]:
    """The state as named arrays (see :func:`state_from_arrays`)."""
    meta = {
        "schema": STATE_SCHEMA,
        "batches_done": state.batches_done,
        "time_s": state.time_s,
        "rng_state": state.rng_state,
        "warnings": list(state.warnings),
        "cache": [list(entry) for entry in state.cache],
        "reshaped": [list(pair) for pair in state.reshaped],
        "floor_reference_mass_g": state.floor_reference_mass_g,
        "full": state.full,
        "extra": state.extra,
    }
    return {
        "meta": _text(meta),
        "pool": _text([shape_record(s) for s in state.pool]),
        "chip_shape": np.asarray(state.chip_shape, dtype=np.int64),
        "chip_batch": np.asarray(state.chip_batch, dtype=np.int64),
        "positions": np.asarray(state.positions, dtype=float).reshape(-1, 3),
        "quaternions": np.asarray(state.quaternions, dtype=float).reshape(-1, 4),
        **_results_to_arrays(state.results),
    }


def state_from_arrays(arrays, where: str = "deposition state") -> DepositionState:
    """Rebuild a :class:`DepositionState`; a damaged record raises InputError naming
    ``where``."""
    meta = _meta(arrays, STATE_SCHEMA, "deposition state", where)
    pool = _shapes_from(arrays, "pool", where)
    try:
        chip_shape = np.asarray(arrays["chip_shape"], dtype=np.int64)
        state = DepositionState(
            batches_done=int(meta["batches_done"]),
            time_s=float(meta["time_s"]),
            rng_state=meta["rng_state"],
            pool=pool,
            chip_shape=chip_shape,
            chip_batch=np.asarray(arrays["chip_batch"], dtype=np.int64),
            positions=np.asarray(arrays["positions"], dtype=float),
            quaternions=np.asarray(arrays["quaternions"], dtype=float),
            results=_results_from_arrays(arrays, where),
            warnings=tuple(str(w) for w in meta["warnings"]),
            cache=tuple((int(k), float(size), int(i)) for k, size, i in meta["cache"]),
            reshaped=tuple((int(a), int(b)) for a, b in meta["reshaped"]),
            floor_reference_mass_g=meta["floor_reference_mass_g"],
            full=bool(meta["full"]),
            extra=dict(meta.get("extra", {})),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: incomplete deposition state ({exc})") from None
    n = len(chip_shape)
    used = [i for i in chip_shape.tolist()] + [i for _, _, i in state.cache]
    used += [i for pair in state.reshaped for i in pair]
    if (
        state.chip_batch.shape != (n,)
        or state.positions.shape != (n, 3)
        or state.quaternions.shape != (n, 4)
        or any(not 0 <= i < len(pool) for i in used)
    ):
        raise InputError(f"{where}: inconsistent deposition state (chip counts or shape indices)")
    return state


def round_trip(state: DepositionState) -> DepositionState:
    """The state as a resumed run would read it back from its file."""
    return state_from_arrays(state_to_arrays(state))


def stack_to_arrays(stack: Stack) -> dict[str, np.ndarray]:
    """A settled stack as named arrays: exact poses of every batch, contacts, shapes."""
    meta = {
        "schema": STACK_SCHEMA,
        "target_size_mm": stack.target_size_mm,
        "warnings": list(stack.warnings),
    }
    return {
        "meta": _text(meta),
        "shapes": _text([shape_record(s) for s in stack.shapes]),
        "shape_index": np.asarray(stack.shape_index, dtype=np.int64),
        "batch": np.asarray(stack.batch, dtype=np.int64),
        **_results_to_arrays(stack.batches, timings=False),
    }


def stack_from_arrays(arrays, where: str = "stack") -> Stack:
    """Rebuild a :class:`Stack` written by :func:`stack_to_arrays`."""
    meta = _meta(arrays, STACK_SCHEMA, "stack record", where)
    shapes = _shapes_from(arrays, "shapes", where)
    try:
        shape_index = np.asarray(arrays["shape_index"], dtype=np.int64)
        batch = np.asarray(arrays["batch"], dtype=np.int64)
        stack = Stack(
            shapes=shapes,
            shape_index=shape_index,
            batch=batch,
            batches=_results_from_arrays(arrays, where),
            target_size_mm=float(meta["target_size_mm"]),
            warnings=tuple(str(w) for w in meta["warnings"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: incomplete stack record ({exc})") from None
    if (
        not stack.batches
        or len(stack.positions) != len(shape_index)
        or len(batch) != len(shape_index)
        or (len(shape_index) and not 0 <= shape_index.min() <= shape_index.max() < len(shapes))
    ):
        raise InputError(f"{where}: inconsistent stack record (chip counts or shape indices)")
    return stack


def load_stack(folder: Path) -> Stack:
    """The stack record (``stack.npz``) back from a written folder."""
    path = folder / "stack.npz"
    try:
        with np.load(path, allow_pickle=False) as arrays:
            return stack_from_arrays(dict(arrays), str(path))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: unreadable stack record ({brief(str(exc))})") from None

"""Contact types per chip (point, line, surface) and the partner's place, after each batch
(the paper's Fig. 7)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from chipstack.export.tables import fmt
from chipstack.geometry.contacts import (
    GROUND,
    KINDS,
    PLACES,
    ContactTable,
    contact_counts,
    find_contacts,
)
from chipstack.geometry.descriptors.base import (
    Context,
    Descriptor,
    Table,
    bands,
    figure_module,
    profile,
    scalar,
)


@dataclass(frozen=True)
class ContactHistory:
    """Contact tables after each batch (NBD 1, 2, ...)."""

    tables: tuple[ContactTable, ...]
    batches: tuple[int, ...]


def _contact_tables(history: ContactHistory) -> dict[str, Table]:
    rows = []
    for batch, table in zip(history.batches, history.tables, strict=True):
        n = max(table.n_chips, 1)
        rows.append(
            [batch, table.n_chips]
            + [fmt(np.sum(table.kind == k) / n) for k in range(len(KINDS))]
            + [fmt(len(table) / n)]
        )
    by_batch = ["batch", "chips"] + [f"{k}_per_chip" for k in KINDS] + ["total_per_chip"]
    final = history.tables[-1]
    places = (*PLACES, "")
    header = ["chip_a", "chip_b", "kind", "extent_1_mm", "extent_2_mm", "extent_3_mm"]
    header += ["x_mm", "y_mm", "z_mm", "area_mm2", "b_seen_from_a", "a_seen_from_b"]
    pairs = (
        [
            int(final.chip_a[k]),
            int(final.chip_b[k]),
            KINDS[final.kind[k]],
            *(fmt(v) for v in final.extents_mm[k]),
            *(fmt(v) for v in final.centre_mm[k]),
            fmt(final.area_mm2[k]),
            places[final.place_a[k]],
            places[final.place_b[k]] if final.place_b[k] >= 0 else "",
        ]
        for k in range(len(final))
    )
    return {"contacts_by_batch.csv": (by_batch, rows), "contacts.csv": (header, pairs)}


def _contact_figures(history: ContactHistory, section: dict[str, Any], folder: Path) -> list[str]:
    figures = figure_module()
    profiles = section["profiles"]
    mean = {kind: np.array(profiles[f"{kind}_per_chip_by_batch"]["values"]) for kind in KINDS}
    batches = np.array(profiles["point_per_chip_by_batch"]["index"])
    figures.plot_contact_types(folder / "contact_types.png", batches, mean)
    return ["contact_types.png"]


def _contact_ensemble_figures(summary: dict[str, Any], folder: Path) -> list[str]:
    """Fig. 7 with 95 % confidence bands over the repeats."""
    figures = figure_module()
    profiles = summary["profiles"]
    batches = np.array(profiles["point_per_chip_by_batch"]["index"])
    mean, low, high = {}, {}, {}
    for kind in KINDS:
        mean[kind], low[kind], high[kind] = bands(profiles[f"{kind}_per_chip_by_batch"])
    figures.plot_contact_types(folder / "contact_types.png", batches, mean, low, high)
    return ["contact_types.png"]


def _contact_columns(history: ContactHistory) -> dict[str, list]:
    counts = contact_counts(history.tables[-1])
    columns = {
        f"{kind}_contacts": counts[:, k].sum(axis=1).tolist() for k, kind in enumerate(KINDS)
    }
    for p, place in enumerate(PLACES):
        columns[f"contacts_{place}"] = counts[:, :, p].sum(axis=1).tolist()
    return columns


def _contact_headline(section: dict[str, Any]) -> str:
    s = section["scalars"]
    return "contacts per chip: " + ", ".join(
        f"{k} {s[k + '_per_chip']['value']:.2f}" for k in KINDS
    )


def _contacts(ctx: Context):
    spec = ctx.spec
    tables = tuple(
        find_contacts(a, spec.contact_gap_mm, spec.contact_extent_mm) for a in ctx.history
    )
    batches = tuple(int(a.batch.max()) if a.n_chips else 0 for a in ctx.history)
    final = tables[-1]
    n = max(final.n_chips, 1)
    counts = contact_counts(final)  # (n, kinds, places), each chip counting its own contacts
    scalars: dict[str, Any] = {}
    for k, kind in enumerate(KINDS):
        scalars[f"{kind}_per_chip"] = scalar(
            np.sum(final.kind == k) / n,
            "1/chip",
            f"{kind} contacts (touching pairs, floor included) divided by the number of chips",
        )
    scalars["total_per_chip"] = scalar(len(final) / n, "1/chip", "all contacts / chips")
    for k, kind in enumerate(KINDS):
        scalars[f"{kind}_per_chip_both_sides"] = scalar(
            counts[:, k].sum() / n,
            "1/chip",
            f"{kind} contacts each chip takes part in, averaged over chips "
            "(a chip-chip contact counts for both chips)",
        )
    for p, place in enumerate(PLACES):
        for k, kind in enumerate(KINDS):
            scalars[f"{kind}_{place}_per_chip"] = scalar(
                counts[:, k, p].sum() / n,
                "1/chip",
                f"{kind} contacts with a partner {place} the chip, per chip (both sides)",
            )
    scalars["ground_contacts"] = scalar(
        np.sum(final.chip_b == GROUND), "", "chips touching the conveyor"
    )
    scalars["mean_patch_area_mm2"] = scalar(
        final.area_mm2.mean() if len(final) else 0.0,
        "mm2",
        "mean area of a contact patch at the gap tolerance",
    )
    profiles = {}
    for k, kind in enumerate(KINDS):
        profiles[f"{kind}_per_chip_by_batch"] = profile(
            list(batches),
            [np.sum(t.kind == k) / max(t.n_chips, 1) for t in tables],
            "batch",
            "1/chip",
            f"{kind} contacts per chip after each batch (NBD), pair convention",
            pad=None,
        )
    return ContactHistory(tables, batches), {"scalars": scalars, "profiles": profiles}


DESCRIPTOR = Descriptor(
    "contacts",
    "contact types per chip (point, line, surface) and partner place, by NBD",
    tables=_contact_tables,
    figures=_contact_figures,
    ensemble_figures=_contact_ensemble_figures,
    chip_columns=_contact_columns,
    headline=_contact_headline,
    ensemble_scalars=tuple(f"{kind}_per_chip" for kind in KINDS),
    order=20,
    compute=_contacts,
)

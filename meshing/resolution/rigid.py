"""Rigid chips for contact resolution: convex pieces placed in the world, their
separating-axis gaps, and the rule each pair keeps (shared by the bottom-up route in
:mod:`.bottom_up` and the global route in :mod:`.relax`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from chipstack.geometry.contacts import GROUND, KINDS, ContactTable
from chipstack.geometry.solids import shape_pieces

SURFACE = KINDS.index("surface")
LINE = KINDS.index("line")
MAX_MOVE_MM = 1.0  # the largest motion asked of a chip (a tenth of its thickness is typical)
MAX_TURN_RAD = np.radians(6.0)
TURN_WEIGHT = 10.0  # turns cost this many times their inertia: a turn sweeps corners far
REACH_MM = 0.3  # pairs further apart than their lower bound by this are left out of a step
CORNER_REACH_MM = 0.2  # corners this close to a pair's extreme are constrained too
SLACK_MM = 2e-4  # margin kept above the gap so rounding cannot bring a pair under it


@dataclass(frozen=True)
class ConvexPiece:
    """A convex piece in its chip's frame: corners, outward face planes, edge directions."""

    vertices: np.ndarray  # (V, 3) mm
    normals: np.ndarray  # (F, 3)
    offsets: np.ndarray  # (F,) mm
    edges: np.ndarray  # (E, 3) unit edge directions, one per parallel family


def _edge_directions(vertices, normals, offsets) -> np.ndarray:
    scale = max(1.0, float(np.abs(vertices).max()))
    on = np.abs(vertices @ normals.T - offsets) < 1e-7 * scale  # (V, F)
    directions: list[np.ndarray] = []
    for a in range(len(normals)):
        for b in range(a + 1, len(normals)):
            if np.count_nonzero(on[:, a] & on[:, b]) < 2:
                continue
            d = np.cross(normals[a], normals[b])
            norm = np.linalg.norm(d)
            if norm < 1e-9:
                continue
            d /= norm
            if not any(abs(float(d @ e)) > 1 - 1e-9 for e in directions):
                directions.append(d)
    return np.array(directions).reshape(-1, 3)


def convex_pieces(shape) -> tuple[ConvexPiece, ...]:
    out = []
    for piece in shape_pieces(shape):
        v, n, d = (
            np.asarray(a, dtype=float) for a in (piece.vertices, piece.normals, piece.offsets)
        )
        out.append(ConvexPiece(v, n, d, _edge_directions(v, n, d)))
    return tuple(out)


@dataclass
class PlacedChip:
    """One chip's pieces placed in the world (for separating-axis tests)."""

    vertices: list[np.ndarray]
    normals: list[np.ndarray]
    edges: list[np.ndarray]
    offsets: list[np.ndarray]  # face planes in the world: normals . x <= offsets


def place_chip(
    pieces: tuple[ConvexPiece, ...], rotation: np.ndarray, position: np.ndarray
) -> PlacedChip:
    vertices = [p.vertices @ rotation.T + position for p in pieces]
    normals = [p.normals @ rotation.T for p in pieces]
    offsets = [p.offsets + n @ position for p, n in zip(pieces, normals, strict=True)]
    return PlacedChip(vertices, normals, [p.edges @ rotation.T for p in pieces], offsets)


def _edge_crosses(ea: np.ndarray, eb: np.ndarray) -> np.ndarray:
    """(len(ea) * len(eb), 3) cross products of every edge of ``ea`` with every edge of
    ``eb``, ``ea``'s index outer. The same arithmetic as ``np.cross``, whose set-up cost
    dominated on these few-row arrays (15.7 of 38 s of building the resolution's rows on
    the reference stack, profiled)."""
    a0, a1, a2 = (ea[:, None, k] for k in range(3))
    b0, b1, b2 = (eb[None, :, k] for k in range(3))
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1).reshape(
        -1, 3
    )


def _piece_separation(va, na, ea, vb, nb, eb) -> float:
    cross = _edge_crosses(ea, eb)
    norms = np.linalg.norm(cross, axis=1)
    cross = cross[norms > 1e-6] / norms[norms > 1e-6, None]
    axes = np.vstack([na, nb, cross])
    pa = va @ axes.T
    pb = vb @ axes.T
    gap = np.maximum(pb.min(axis=0) - pa.max(axis=0), pa.min(axis=0) - pb.max(axis=0))
    return float(gap.max())


def separation_between(a: PlacedChip, b: PlacedChip) -> float:
    """Separating-axis distance of two placed chips (mm): positive, a lower bound on the
    distance between them; negative, minus the depth of their deepest interpenetration."""
    return min(
        _piece_separation(va, na, ea, vb, nb, eb)
        for va, na, ea in zip(a.vertices, a.normals, a.edges, strict=True)
        for vb, nb, eb in zip(b.vertices, b.normals, b.edges, strict=True)
    )


def pair_rules(
    contacts: ContactTable, gap_mm: float, contact_gap_mm: float, touching_lines: bool = False
):
    """rule(chip, partner) -> :class:`Rule` for a pair (partner GROUND: the conveyor),
    from its class in the settled stack. ``touching_lines``: a line contact between two
    chips is kept touching (its edge laid parallel on its partner) instead of cleared."""
    kinds = {
        (int(min(a, b)), int(max(a, b))): int(k)
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
    }
    # Touching pairs stay within the contact gap (less a tenth, for rounding) when the
    # clearance leaves room for it.
    within = 0.9 * contact_gap_mm
    upper = within if within > gap_mm + 0.005 else np.inf
    # A pair apart must stay apart for the geometry stage's test too, which inflates each
    # box by half the contact gap along its face normals: along a diagonal axis a corner
    # grows by sqrt(3) times that.
    apart = Rule(max(gap_mm, 1.05 * np.sqrt(3) * contact_gap_mm))

    def rule(chip: int, partner: int) -> Rule:
        kind = kinds.get((min(chip, partner), max(chip, partner)))
        if kind is None:
            return apart
        if touching_lines and kind == LINE and GROUND not in (chip, partner):
            return Rule(0.0, within, True, touching=True)  # touching leaves room for it
        return Rule(gap_mm, upper, kind != KINDS.index("point"))

    return rule


class Rule(NamedTuple):
    """What a pair must keep: a separation of at least ``lower`` and at most ``upper``
    (mm; the settled pair's contact class is kept: a touching pair stays within the
    contact gap, a pair apart stays apart), and, for a line or surface contact cleared
    by the gap, the touching edge or face ``parallel`` to its partner at that gap."""

    lower: float
    upper: float = np.inf
    parallel: bool = False
    touching: bool = False  # a line contact kept touching: its edge laid on the partner


def _axes(na, ea, nb, eb):
    cross = _edge_crosses(ea, eb)
    norms = np.linalg.norm(cross, axis=1)
    valid = norms > 1e-6
    cross = np.where(valid[:, None], cross / np.where(valid, norms, 1.0)[:, None], 0.0)
    return np.vstack([na, nb, cross]), np.concatenate([np.ones(len(na) + len(nb), bool), valid])


def axis_gaps(va, na, ea, vb, nb, eb):
    """Gap along every separating axis (mm; -inf for degenerate ones) and on which side
    of the chip the neighbour lies along it (True: the positive side)."""
    axes, valid = _axes(na, ea, nb, eb)
    pa, pb = va @ axes.T, vb @ axes.T
    ahead = pb.min(axis=0) - pa.max(axis=0)
    behind = pa.min(axis=0) - pb.max(axis=0)
    gaps = np.where(valid, np.maximum(ahead, behind), -np.inf)
    return gaps, ahead >= behind


def batched_axis_gaps(worlds: list[PlacedChip], pairs: list[tuple[int, int]]):
    """:func:`axis_gaps` of every piece of ``a`` against every piece of ``b`` for every
    pair (a, b), computed together: a list per pair of (piece of a, piece of b, gaps,
    sides). Pieces with the same numbers of corners, faces and edges are stacked, and the
    arithmetic is written out element by element (the same on every CPU, where a matrix
    product's rounding depends on the BLAS kernel); one call per chip pair was most of the
    global route's time (reference stack: 119,058 calls, 6.9 of 27.6 s)."""
    entries: dict[tuple, list[tuple[int, int, int]]] = {}
    for index, (a, b) in enumerate(pairs):
        wa, wb = worlds[a], worlds[b]
        for pa in range(len(wa.vertices)):
            for pb in range(len(wb.vertices)):
                kind = (
                    wa.vertices[pa].shape[0],
                    wa.normals[pa].shape[0],
                    wa.edges[pa].shape[0],
                    wb.vertices[pb].shape[0],
                    wb.normals[pb].shape[0],
                    wb.edges[pb].shape[0],
                )
                entries.setdefault(kind, []).append((index, pa, pb))
    out: list[list] = [[] for _ in pairs]
    for group in entries.values():

        def stacked(which: str, side: int, group=group) -> np.ndarray:
            return np.stack(
                [getattr(worlds[pairs[i][side]], which)[(p, q)[side]] for i, p, q in group]
            )

        va, na, ea = stacked("vertices", 0), stacked("normals", 0), stacked("edges", 0)
        vb, nb, eb = stacked("vertices", 1), stacked("normals", 1), stacked("edges", 1)
        a0, a1, a2 = (ea[:, :, None, k] for k in range(3))
        b0, b1, b2 = (eb[:, None, :, k] for k in range(3))
        cross = np.stack(
            [a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1
        ).reshape(len(group), -1, 3)
        norms = np.sqrt(cross[..., 0] ** 2 + cross[..., 1] ** 2 + cross[..., 2] ** 2)
        valid = norms > 1e-6
        cross = np.where(valid[..., None], cross / np.where(valid, norms, 1.0)[..., None], 0.0)
        axes = np.concatenate([na, nb, cross], axis=1)  # (G, K, 3)
        faces = np.ones((len(group), na.shape[1] + nb.shape[1]), bool)
        valid = np.concatenate([faces, valid], axis=1)

        pa, pb = _project(va, axes), _project(vb, axes)
        ahead = pb.min(axis=1) - pa.max(axis=1)
        behind = pa.min(axis=1) - pb.max(axis=1)
        gaps = np.where(valid, np.maximum(ahead, behind), -np.inf)
        sides = ahead >= behind
        for row, (i, p, q) in enumerate(group):
            out[i].append((p, q, gaps[row], sides[row]))
    for items in out:
        items.sort(key=lambda item: item[:2])
    return out


def _project(v: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(G, V, K) projections of corners (G, V, 3) on axes (G, K, 3), term by term."""
    return (
        v[:, :, None, 0] * axes[:, None, :, 0]
        + v[:, :, None, 1] * axes[:, None, :, 1]
        + v[:, :, None, 2] * axes[:, None, :, 2]
    )


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.array(
        [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    )


def separating_axis(world, other, a, b, k) -> np.ndarray:
    """Separating axis ``k`` of piece ``a`` of the chip and piece ``b`` of a neighbour
    (the order of :func:`_axes`)."""
    na, ea, nb, eb = world.normals[a], world.edges[a], other.normals[b], other.edges[b]
    if k < len(na):
        return na[k]
    if k < len(na) + len(nb):
        return nb[k - len(na)]
    i, j = divmod(k - len(na) - len(nb), len(eb))
    axis = _cross(ea[i], eb[j])
    return axis / np.sqrt(axis @ axis)

"""Contact resolution of the whole stack at once (the first route of
:func:`.resolve.resolve_contacts`).

Every chip moves at the same time: sequential quadratic programming over the six rigid
motions of all chips, each step one sparse convex quadratic programme (Clarabel's
interior-point solver) linearised at the current poses:

* the objective is the mass-weighted squared motion of every chip from where the physics
  left it (translations in mm, turns weighted by the chip's inertia);
* a surface contact is a set of equalities: the corners of the chip's face lie in its
  partner's face plane (the conveyor: z = 0);
* every other near pair keeps its rule (:class:`.rigid.Rule`): at least the gap
  along its separating axis, every corner near the extreme a row of its own; a touching
  pair at most the contact gap, a line contact's edge parallel;
* every row is soft with an exact (L1) penalty, the lower bounds and the surface
  contacts heavily so, so that each programme is feasible and the solution meets them
  exactly when they can be met; each step stays in a trust region.

Solving everything at once is what the bottom-up route cannot do: there, a chip placed
early is held while a chip resting on it would need it to give a few hundredths of a
millimetre, and the later chip has to turn by degrees instead. A surface contact whose
equalities cannot hold with the others (a chip lying on two faces that are not coplanar)
is let go and cleared by the gap like any pair; the faces are then made exactly coplanar
by a final snap, chip by chip from the bottom up, of a few nanometres.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from chipstack.geometry.contacts import GROUND, candidate_pairs
from chipstack.meshing.resolution.relax_qp import _metric, _motion_caps, _qp
from chipstack.meshing.resolution.relax_rows import (
    _across_edge,
    _face_edges,
    _facing_faces,
    _floor_rows,
    _misalignment,
    _near_corners,
    _near_flush,
    _pair_rows,
    _Row,
    _shortfalls,
    _stuck_groups,
    _surface_rows,
    _unmet,
    _violation,
)
from chipstack.meshing.resolution.relax_settings import (
    _ALIGN_DEG,
    _ALIGN_PENALTY,
    _CHECKPOINTS,
    _EDGE_PENALTY,
    _EXTENSIONS,
    _EXTRA_ITERATIONS,
    _FLUSH_MM,
    _ITERATIONS,
    _POLISH_RADIUS,
    _POLISH_STEPS,
    _STATIONARY,
)
from chipstack.meshing.resolution.rigid import (
    SURFACE,
    batched_axis_gaps,
    convex_pieces,
    pair_rules,
    place_chip,
)

log = logging.getLogger(__name__)


class Relaxed(NamedTuple):
    """What the global route leaves: every chip's pose (rotations (n, 3, 3), positions
    (n, 3) mm) and the poses it started from, the surface contacts it held, as
    {(chip, partner): ((piece, face) of the chip, (piece, face) of the partner or None
    for the conveyor)}, those it let go, and ``worst``: how far the worst lower bound (or
    surface contact out of its plane) is short of its target (mm; >= 0: none)."""

    rotations: np.ndarray
    positions: np.ndarray
    start_rotations: np.ndarray
    start_positions: np.ndarray
    surface: dict
    let_go: set
    worst: float


def relax(
    arrangement,
    contacts,
    gap_mm: float,
    snap_angle_deg: float,
    contact_gap_mm: float,
    touching_lines: bool = False,
) -> Relaxed | None:
    """Resolve every chip at once (see the module docstring); None when a programme
    fails."""
    return _Relaxation(
        arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines
    ).run()


class _Relaxation:
    """The global route's state: every chip's pose and accumulated motion, the surface
    contacts held and let go, the edges made flush and corners kept off edges, the trust
    region and the step budget."""

    def __init__(
        self, arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines
    ):
        n = self.n = arrangement.n_chips
        self.arrangement = arrangement
        self.pieces = [convex_pieces(s) for s in arrangement.shapes]
        self.rotations = np.array(arrangement.rotations, dtype=float).reshape(n, 3, 3)
        self.positions = np.array(arrangement.positions, dtype=float).reshape(n, 3)
        self.start_rot, self.start_pos = self.rotations.copy(), self.positions.copy()
        rank = arrangement.bottom_up_rank()
        self.rule = pair_rules(contacts, gap_mm, contact_gap_mm, touching_lines)
        cos_snap = np.cos(np.radians(snap_angle_deg))
        volumes = np.array(
            [arrangement.shapes[arrangement.shape_index[k]].volume_mm3 for k in range(n)]
        )
        weights = volumes / volumes.mean()
        inertia = [arrangement.shapes[arrangement.shape_index[k]].inertia_mm2 for k in range(n)]
        self.worlds = [self._world(k) for k in range(n)]
        worlds, rotations = self.worlds, self.rotations
        self.near = [(int(a), int(b)) for a, b in candidate_pairs(arrangement.bounds, gap_mm + 1.0)]
        # Surface contacts: (chip, partner) with the partner placed first (or the conveyor).
        self.surface = {}
        for a, b, kind in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True):
            if kind != SURFACE:
                continue
            a, b = int(a), int(b)
            if b != GROUND and rank[b] > rank[a]:
                a, b = b, a
            faces = _facing_faces(worlds, a, b, contacts, self.positions, cos_snap)
            if faces is not None:
                self.surface[(a, b)] = faces
        self.align = {
            pair
            for pair in self.surface
            if pair[1] != GROUND
            # Asked of the geometry, not of the shape's name: a beam crossing a box at 1.7
            # deg left a wedge no mesh could take (mixed-shapes seed 3).
            and all(arrangement.shapes[arrangement.shape_index[k]].is_cuboid for k in pair)
            and abs(_misalignment(rotations, *pair, worlds, self.surface[pair]))
            < np.radians(_ALIGN_DEG)
        }
        # Edges of two aligned chips that run parallel a hair apart cut the shared face into
        # a strip as narrow: they are made flush (collinear) instead.
        self.flush = _near_flush(worlds, self.surface, self.align, set())
        # A corner a hair from the other face's edge (the edges crossing at a real angle)
        # leaves a neck as narrow in the face around it: it is moved away from the edge's
        # line, on the side it is on, to the flush distance. (Put exactly on the line, it
        # left degenerate tetrahedra: OpenCASCADE merges within its own tolerance.)
        # Corners are looked for again whenever the rest has settled: the motions can bring
        # a corner near an edge that was far from it at the start.
        self.corner_on_edge = _near_corners(worlds, self.surface, self.align, set())
        self.let_go: set = set()
        self.dropped: set = set()
        self.chosen: dict = {}
        # The rotations the rows are built at (a trial step's, while it is tried).
        self.row_rotations = rotations
        self.metric = _metric(self.start_rot, inertia, weights)
        self.caps = _motion_caps(worlds, gap_mm, arrangement.thinnest_mm)  # up, down
        self.total = np.zeros(6 * n)  # accumulated motion (translation, rotation vector)
        self.radius = 1.0  # trust region, in units of (_STEP_MM, _STEP_RAD)
        self.rows = self.build(worlds)
        self.current = self.merit(self.rows, self.total)
        self.limit, self.extended = _ITERATIONS, 0
        self.iteration = -1
        self.checkpoint, self.last_checkpoint = 0, -1
        # An edge rule's offset when first seen or at the last checkpoint.
        self.edge_offsets: dict = {}

    def _world(self, k: int, rotation=None, position=None):
        return place_chip(
            self.pieces[self.arrangement.shape_index[k]],
            self.rotations[k] if rotation is None else rotation,
            self.positions[k] if position is None else position,
        )

    def kept(self) -> dict:
        """The surface contacts held: {(chip, partner): faces}."""
        return {pair: f for pair, f in self.surface.items() if pair not in self.let_go}

    def build(self, worlds) -> list[_Row]:
        """Every row at the poses ``worlds``: pairs and the conveyor, the surface contacts
        held (and their alignments), the edges made flush and the corners kept off
        edges."""
        kept = self.kept()
        return (
            self._pair_and_floor_rows(worlds, kept)
            + self._surface_rows(worlds, kept)
            + self._flush_rows(worlds, kept)
            + self._corner_rows(worlds, kept)
        )

    def _pair_and_floor_rows(self, worlds, kept) -> list[_Row]:
        equal_pairs = {frozenset(p) for p in kept}
        rows = []
        pairs = [(a, b) for a, b in self.near if frozenset((a, b)) not in equal_pairs]
        for (a, b), gaps in zip(pairs, batched_axis_gaps(worlds, pairs), strict=True):
            rows += _pair_rows(worlds, a, b, self.rule(a, b), self.chosen, gaps)
        for k in range(self.n):
            if (k, GROUND) not in kept:
                rows += _floor_rows(worlds[k], k, self.rule(k, GROUND))
        return rows

    def _surface_rows(self, worlds, kept) -> list[_Row]:
        rows = []
        for (a, b), (face_a, face_b) in kept.items():
            rows += _surface_rows(worlds, a, b, face_a, face_b)
            if (a, b) in self.align and ("align", a, b) not in self.dropped:
                normal = worlds[b].normals[face_b[0]][face_b[1]]
                value = _misalignment(self.row_rotations, a, b, worlds, (face_a, face_b))
                rows.append(
                    _Row(
                        a,
                        b,
                        normal,
                        normal,
                        normal,
                        value,
                        0,
                        0.0,
                        _ALIGN_PENALTY,
                        turn=True,
                        key=("align", a, b),
                    )
                )
        return rows

    def _flush_rows(self, worlds, kept) -> list[_Row]:
        rows = []
        for (a, b), i, j in self.flush:
            if (a, b) not in kept or ("flush", a, b, i, j) in self.dropped:
                continue
            (pa, fa), (pb, fb) = kept[(a, b)]
            p, q = _face_edges(worlds[a], pa, fa)[i]
            s_, t = _face_edges(worlds[b], pb, fb)[j]
            middle = (p + q) / 2
            across, foot = _across_edge(middle, s_, t, worlds[b].normals[pb][fb])
            value = float(across @ (middle - foot))
            rows.append(
                _Row(
                    b,
                    a,
                    across,
                    foot,
                    middle,
                    value,
                    0,
                    0.0,
                    _EDGE_PENALTY,
                    key=("flush", a, b, i, j),
                )
            )
        return rows

    def _corner_rows(self, worlds, kept) -> list[_Row]:
        rows = []
        for pair, first, i, j, side in self.corner_on_edge:
            if pair not in kept or ("corner", pair, first, i, j) in self.dropped:
                continue
            faces = kept[pair]
            own, other = pair[first], pair[1 - first]
            corner = _face_edges(worlds[own], *faces[first])[i][0]
            s_, t = _face_edges(worlds[other], *faces[1 - first])[j]
            normal = worlds[pair[1]].normals[faces[1][0]][faces[1][1]]
            across, foot = _across_edge(corner, s_, t, normal)
            away = side * across
            value = float(away @ (corner - foot))
            rows.append(
                _Row(
                    other,
                    own,
                    away,
                    foot,
                    corner,
                    value,
                    1,
                    _FLUSH_MM,
                    _EDGE_PENALTY,
                    key=("corner", pair, first, i, j),
                )
            )
        return rows

    def merit(self, rows, total) -> float:
        return 0.5 * float(total @ (self.metric @ total)) + sum(
            row.penalty * _violation(row) for row in rows
        )

    def _let_go_stuck_surfaces(self) -> bool:
        """At the end of the budget (or of the trust region): the surface contacts that
        hold the rest up are let go and the rest given more steps (a few times)."""
        stuck = _stuck_groups(self.rows)
        if self.extended >= _EXTENSIONS or not stuck:
            return False
        self.extended += 1
        self.let_go.update(stuck)
        self.rows = self.build(self.worlds)
        self.current = self.merit(self.rows, self.total)
        self.radius = 1.0
        self.limit = self.iteration + 1 + _EXTRA_ITERATIONS
        log.debug("relax: %d surface contacts let go at step %d", len(stuck), self.iteration)
        return True

    def run(self) -> Relaxed | None:
        while True:
            self.iteration += 1
            if self.iteration >= self.limit and not self._let_go_stuck_surfaces():
                self._polish()
                break
            for row in self.rows:
                if row.key is not None:
                    self.edge_offsets.setdefault(row.key, _violation(row))
            worst, off_plane, turned = _shortfalls(self.rows)
            # The lower bounds carry a margin (SLACK_MM) above the gap: a micrometre
            # short of it is still clear, and the final check is against the gap.
            # 1e-8 mm: within OpenCASCADE's tolerance (1e-7), so that a chip's second
            # partner face, which the final snap does not move, merges with its face.
            if worst >= -1e-6 and off_plane < 1e-8 and turned < 1e-8:
                if not self._new_edges():
                    break
                continue
            stepped = self._step(worst, off_plane)
            if stepped is None:
                log.debug("relax: programme failed at step %d", self.iteration)
                return None
            if not stepped:
                break
            self._checkpoint()
        return self._result()

    def _new_edges(self) -> bool:
        """Once the rest has settled: corners and edges the motions brought near an edge
        of a shared face, added as rules of their own (False: none)."""
        known = {entry[:4] for entry in self.corner_on_edge}
        kept = self.kept()
        new = [
            entry
            for entry in _near_corners(self.worlds, kept, self.align, known)
            if ("corner", *entry[:4]) not in self.dropped
        ]
        # Edges the motions brought within the flush distance are made flush too: two
        # aligned chips 0.56 mm apart sideways at the start ended 0.5 um apart, a strip no
        # mesh can take (paper-rectangles, seed 2).
        new_flush = [
            entry
            for entry in _near_flush(self.worlds, kept, self.align, set(self.flush))
            if ("flush", *entry[0], *entry[1:]) not in self.dropped
        ]
        if not new and not new_flush:
            return False
        self.corner_on_edge += new
        self.flush += new_flush
        self.rows = self.build(self.worlds)
        self.current = self.merit(self.rows, self.total)
        self.radius = 1.0
        return True

    def _step(self, worst: float, off_plane: float) -> bool | None:
        """One programme and its trial step, taken when the true merit falls; the trust
        region updated. None: the programme failed; False: nothing more to gain."""
        solved = _qp(self.rows, self.total, self.metric, self.positions, self.caps, self.radius)
        if solved is None:
            return None
        delta, modelled = solved
        predicted = self.current - modelled
        trial_rot, trial_pos, trial_worlds, trial_rows = self._trial(delta)
        trial = self.merit(trial_rows, self.total + delta)
        log.debug(
            "relax step %d: %d rows, worst lower %.2e mm, off plane %.2e mm, radius %.3g, "
            "merit %.6g -> %.6g",
            self.iteration,
            len(self.rows),
            worst,
            off_plane,
            self.radius,
            self.current,
            trial,
        )
        # The trust region grows only when the model predicted the gain well: doubling it
        # after every accepted step had every other step rejected, the rotations' curvature
        # costing more than the step gained (reference stack: 79 programmes, half wasted).
        ratio = (self.current - trial) / predicted if predicted > 0 else 0.0
        if trial < self.current:
            self.rotations, self.positions, self.worlds = trial_rot, trial_pos, trial_worlds
            self.row_rotations = self.rotations
            self.total = self.total + delta
            self.rows, self.current = trial_rows, trial
            if ratio > 0.75:
                self.radius = min(1.0, 2 * self.radius)
            elif ratio < 0.25:
                self.radius /= 2
        else:
            self.radius /= 4
            if self.radius < 1e-6 and not self._let_go_stuck_surfaces():
                self._polish()
                return False
        return True

    def _trial(self, delta):
        """Poses, placed chips and rows after the step ``delta``."""
        n, pieces, arrangement = self.n, self.pieces, self.arrangement
        trial_rot, trial_pos = self.rotations.copy(), self.positions.copy()
        trial_worlds = list(self.worlds)
        for k in np.flatnonzero(np.abs(delta.reshape(n, 6)).max(axis=1) > 0):
            t, w = delta[6 * k : 6 * k + 3], delta[6 * k + 3 : 6 * k + 6]
            trial_rot[k] = Rotation.from_rotvec(w).as_matrix() @ self.rotations[k]
            trial_pos[k] = self.positions[k] + t
            trial_worlds[k] = place_chip(
                pieces[arrangement.shape_index[k]], trial_rot[k], trial_pos[k]
            )
        self.row_rotations = trial_rot
        trial_rows = self.build(trial_worlds)
        self.row_rotations = self.rotations
        return trial_rot, trial_pos, trial_worlds, trial_rows

    def _polish(self) -> None:
        """A few tiny steps that only restore the lower bounds and the surface contacts,
        without the pull back towards the start: when the budget runs out the motion
        objective may still be creeping, and each of its steps leaves the rows a few
        1e-8 mm off by the turns' curvature, more than the 1e-8 mm a second partner face
        may be off (paper-rectangles, seed 0, with 2 mm caps: 3e-8 mm). A step is kept
        only when it brings the rows closer (the surface corners counted 100 times: their
        tolerance is a hundredth of the lower bounds')."""
        for _ in range(_POLISH_STEPS):
            short, off = _unmet(self.rows)
            if short < 1e-6 and off < 1e-8:
                return
            solved = _qp(
                self.rows,
                self.total,
                self.metric,
                self.positions,
                self.caps,
                _POLISH_RADIUS,
                anchor=False,
            )
            if solved is None:
                return
            delta = solved[0]
            trial_rot, trial_pos, trial_worlds, trial_rows = self._trial(delta)
            trial_short, trial_off = _unmet(trial_rows)
            if max(trial_short, 100 * trial_off) >= max(short, 100 * off):
                return
            self.rotations, self.positions, self.worlds = trial_rot, trial_pos, trial_worlds
            self.rows, self.row_rotations = trial_rows, trial_rot
            self.total = self.total + delta
            self.current = self.merit(self.rows, self.total)
            log.debug("relax: polished to %.3g mm short, %.3g mm off plane", *_unmet(self.rows))

    def _checkpoint(self) -> None:
        """What cannot hold with the rest once it has settled is let go: first an edge
        made flush or a corner put on an edge (the mesh copes with a narrow strip better
        than the stack with a lost contact), then, later, a surface contact still out of
        its plane (cleared by the gap instead).

        A checkpoint comes at its step or, sooner, once the trust region has shrunk to
        nothing (the rest has settled: waiting for the fixed step only spent programmes on
        a merit that no longer moves, 15 of them on the reference stack, seed 0)."""
        due = self.checkpoint < len(_CHECKPOINTS) and (
            self.iteration >= _CHECKPOINTS[self.checkpoint]
            or (self.radius <= _STATIONARY and self.iteration - self.last_checkpoint >= 4)
        )
        if not due:
            return
        # An edge that has not halved its offset since the last checkpoint is stuck; one
        # still closing is kept: let go a few micrometres from flush, it would leave a
        # strip that thin for the mesh (the reference stack, seed 1: an alignment let go
        # at 4e-4 rad left an 8 um wedge along a 20 mm edge, and triangles of quality 0.05
        # on it).
        stuck_edges = set()
        for row in self.rows:
            if row.key is not None:
                offset = _violation(row)
                if offset > 1e-6 and offset > 0.5 * self.edge_offsets.get(row.key, 0.0):
                    stuck_edges.add(row.key)
                self.edge_offsets[row.key] = offset
        stuck = set() if self.checkpoint == 0 else _stuck_groups(self.rows)
        self.checkpoint, self.last_checkpoint = self.checkpoint + 1, self.iteration
        if not (stuck or stuck_edges):
            return
        log.debug(
            "relax: checkpoint at step %d: let go %s, %s",
            self.iteration,
            sorted(stuck),
            sorted(
                (key, round(_violation(row), 6))
                for row in self.rows
                if row.key in stuck_edges
                for key in [row.key]
            ),
        )
        self.let_go.update(stuck)
        self.dropped.update(stuck_edges)
        self.rows = self.build(self.worlds)
        self.current = self.merit(self.rows, self.total)
        self.radius = 1.0

    def _result(self) -> Relaxed:
        worst, off_plane, _ = _shortfalls(self.rows)
        # A surface contact left out of its plane would be snapped into it afterwards, by
        # as much: that counts against the result like a pair short of its gap.
        worst = min(worst, -off_plane if off_plane > 1e-5 else 0.0)
        return Relaxed(
            self.rotations,
            self.positions,
            self.start_rot,
            self.start_pos,
            self.surface,
            self.let_go,
            worst,
        )

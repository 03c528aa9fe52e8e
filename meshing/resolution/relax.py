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

import dataclasses
import logging
from dataclasses import dataclass
from typing import NamedTuple

import clarabel
import numpy as np
import scipy.sparse as sparse
from scipy.spatial.transform import Rotation

from chipstack.geometry.contacts import GROUND, candidate_pairs
from chipstack.meshing.resolution.result import Resolution
from chipstack.meshing.resolution.rigid import (
    CORNER_REACH_MM,
    MAX_MOVE_MM,
    MAX_TURN_RAD,
    REACH_MM,
    SLACK_MM,
    SURFACE,
    TURN_WEIGHT,
    batched_axis_gaps,
    convex_pieces,
    pair_rules,
    place_chip,
    separating_axis,
    separation_between,
)
from chipstack.meshing.resolution.snapping import TOUCHING_TOL_MM, snap, verify_rules

log = logging.getLogger(__name__)

_LOWER_PENALTY = 1e5  # per mm below a lower bound
_SURFACE_PENALTY = 1e4  # per mm out of a surface contact's plane
_SOFT_PENALTY = 1e3  # per mm beyond an upper bound or off parallel (keeps contact classes)
# Per mm of a touching line contact's edge off its partner. Softer than the rest: a chip
# lying flat on one partner cannot always lay an edge exactly on another as well, and the
# surface contact comes first (reference stack, seed 0: at 1e3 twice the surface contacts
# were let go; at 1e4 three chips could not be resolved).
_TOUCHING_PENALTY = 1e2
# Per radian off alignment: as strong as the edge penalty (per mm) at the end of a 10 mm
# lever. At 1e3 a radian (5e1 a millimetre there) the alignment of a chip resting on
# others stalled a few 1e-4 rad short, and was let go as a wedge that thin (reference
# stack, seed 1).
_ALIGN_PENALTY = 1e4
_EDGE_PENALTY = 1e3  # per mm off flush, or of a corner short of its distance from an edge
# Two chips in a shared plane whose outlines cross at less than this are turned (about
# the plane's normal) until their edges are parallel: outlines crossing at a shallow
# angle cut the shared face into a thin wedge, and no tetrahedron on it can be sound.
_ALIGN_DEG = 6.0
_EXTRA_ITERATIONS = 30  # steps given after stuck surface contacts are let go at the end
_EXTENSIONS = 3  # at most this many times
_FLUSH_MM = 0.3  # parallel edges closer than this in a shared plane are made flush
_STEP_MM = 0.1  # trust region per step
_STEP_RAD = 0.01
_ITERATIONS = 80
_CHECKPOINTS = (12, 24, 40)  # steps at which what cannot hold is let go
_STATIONARY = 1 / 64  # a trust region this small: the step has settled (a checkpoint)
_POLISH_STEPS = 5  # at most this many restoring steps when the budget runs out
_POLISH_RADIUS = 1e-4  # their trust region: second-order errors ~1e-11 mm


@dataclass
class _Row:
    """One linearised constraint: value = n . (x_b - x_a) of a point x_a on chip ``a``
    (-1: the conveyor) and x_b on chip ``b``; sense +1: value >= target, -1: <=, 0: ==;
    ``group``: the surface contact it belongs to (None: not a surface equality)."""

    a: int
    b: int
    normal: np.ndarray
    x_a: np.ndarray
    x_b: np.ndarray
    value: float
    sense: int
    target: float
    penalty: float
    group: object = None
    turn: bool = False  # a turn about ``normal``: d value = (w_b - w_a) . normal
    key: object = None  # an alignment, flush edge or corner on an edge (can be let go)


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


def resolve_globally(
    arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines=False
):
    """The global route (:func:`relax`) finished by an exact snap of every kept
    surface contact, bottom-up; None when it leaves any pair short of its rule."""
    out = relax(arrangement, contacts, gap_mm, snap_angle_deg, contact_gap_mm, touching_lines)
    # The relaxation's bounds carry the slack above the gap: a pair short of them by less
    # than the slack is still clear, and the check below is against the gap itself (half
    # the slack turned mixed-shapes, seed 0, over to the bottom-up route, which took more
    # than 25 minutes and failed, for a pair 0.1 um short of the slack and clear).
    if out is None or out.worst < -SLACK_MM:
        return None
    rotations, positions, start_rot, start_pos, surface, let_go, _ = out
    n = arrangement.n_chips
    pieces = [convex_pieces(s) for s in arrangement.shapes]
    rank = arrangement.bottom_up_rank()
    order = arrangement.bottom_up_order()
    rule = pair_rules(contacts, gap_mm, contact_gap_mm, touching_lines)
    cos_snap = np.cos(np.radians(snap_angle_deg))
    kept = [pair for pair in surface if pair not in let_go]
    partners: dict[int, list[int]] = {k: [] for k in range(n)}
    touching: dict[int, set[int]] = {k: set() for k in range(n)}
    for chip, partner in kept:
        partners[chip].append(partner)
        touching[chip].add(partner)
        if partner != GROUND:
            touching[partner].add(chip)
    placed = [
        place_chip(pieces[arrangement.shape_index[k]], rotations[k], positions[k]) for k in range(n)
    ]
    for chip in order:
        chip = int(chip)
        if not partners[chip]:
            continue
        # The first partner's face exactly: the relaxation leaves it nanometres off.
        partner = min(partners[chip], key=lambda k: -1 if k == GROUND else rank[k])
        faces = surface[(chip, partner)]
        if partner == GROUND:
            plane = (np.array([0.0, 0.0, 1.0]), 0.0, positions[chip] * [1, 1, 0])
        else:
            piece, face = faces[1]
            world = placed[partner]
            plane = (world.normals[piece][face], float(world.offsets[piece][face]), positions[chip])
        snapped = snap(
            pieces[arrangement.shape_index[chip]], rotations[chip], positions[chip], plane, cos_snap
        )
        if snapped is None:
            return None
        rotations[chip], positions[chip] = snapped
        placed[chip] = place_chip(pieces[arrangement.shape_index[chip]], *snapped)
    near: dict[int, set[int]] = {k: set() for k in range(n)}
    for a, b in candidate_pairs(arrangement.bounds, gap_mm + 1.0):
        near[int(a)].add(int(b))
        near[int(b)].add(int(a))
    unresolved = verify_rules(order, near, placed, touching, rule, touching_tol=TOUCHING_TOL_MM)
    if unresolved:
        log.info("contact resolution, global route: %d chips short", len(unresolved))
        return None
    start_worlds = [
        place_chip(pieces[arrangement.shape_index[k]], start_rot[k], start_pos[k]) for k in range(n)
    ]
    cleared = sum(
        1
        for a in range(n)
        for b in near[a]
        if a < b and separation_between(start_worlds[a], start_worlds[b]) < rule(a, b).lower
    )
    resolved = dataclasses.replace(
        arrangement, positions=positions, quaternions=Rotation.from_matrix(rotations).as_quat()
    )
    turned = (Rotation.from_matrix(rotations) * Rotation.from_matrix(start_rot).inv()).magnitude()
    surface_pairs = [
        (int(a), int(b))
        for a, b, k in zip(contacts.chip_a, contacts.chip_b, contacts.kind, strict=True)
        if k == SURFACE
    ]
    kept_sets = {frozenset(p) for p in kept}
    return Resolution(
        arrangement=resolved,
        translation_mm=np.linalg.norm(positions - start_pos, axis=1),
        rotation_deg=np.degrees(turned),
        snapped={
            "chip": sum(1 for _, p in kept if p != GROUND),
            "conveyor": sum(1 for _, p in kept if p == GROUND),
        },
        surface_cleared=tuple(p for p in surface_pairs if frozenset(p) not in kept_sets),
        cleared=cleared,
        gap_mm=gap_mm,
        snap_angle_deg=snap_angle_deg,
        info={"route": "global"},
    )


def _motion_caps(worlds, gap_mm: float, thinnest_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(6 n,) how far each chip may move from where the physics left it, up and down each
    axis: the bottom-up route's limit, and upwards one gap more per chip thickness between
    the chip and the conveyor, since every contact cleared below a chip lifts it by a gap.

    With the same 1 mm everywhere, a dense stack cleared by 0.2 mm (paper-rectangles,
    seed 0) had 128 of its 270 chips at the limit by step 24, 46 of them upwards: the
    surface contacts let go there could not be cleared, the chips above them being unable
    to rise, and pairs were left 0.25 mm into each other."""
    n = len(worlds)
    lowest = np.array([min(float(v[:, 2].min()) for v in w.vertices) for w in worlds])
    down = np.tile(np.r_[[MAX_MOVE_MM] * 3, [MAX_TURN_RAD] * 3], (n, 1))
    up = down.copy()
    up[:, 2] += gap_mm * np.maximum(lowest, 0.0) / thinnest_mm
    return up.ravel(), down.ravel()


def _across_edge(point, s, t, normal):
    """The unit direction across edge s-t in the plane of ``normal``, and the foot of
    ``point`` on the edge's line."""
    edge = (t - s) / np.linalg.norm(t - s)
    return np.cross(normal, edge), s + edge * ((point - s) @ edge)


def _unmet(rows) -> tuple[float, float]:
    """(mm) the worst lower bound short of its target and the surface corner furthest out
    of its plane: what the result is judged by."""
    worst, off, _ = _shortfalls(rows)
    return max(0.0, -worst), off


def _shortfalls(rows) -> tuple[float, float, float]:
    """The worst lower bound's margin (mm; negative: short), the furthest surface contact
    out of its plane (mm) and the largest edge rule's violation."""
    worst = min(
        (row.value - row.target for row in rows if row.penalty == _LOWER_PENALTY),
        default=np.inf,
    )
    off_plane = max((abs(row.value) for row in rows if row.group is not None), default=0.0)
    turned = max((_violation(row) for row in rows if row.key is not None), default=0.0)
    return worst, off_plane, turned


def _stuck_groups(rows) -> set:
    """The surface contacts out of their plane by more than 10 um and by more than a tenth
    of the worst one: the ones that hold the rest up, not those still on their way."""
    off = {}
    for row in rows:
        if row.group is not None:
            off[row.group] = max(off.get(row.group, 0.0), abs(row.value))
    worst = max(off.values(), default=0.0)
    return {group for group, value in off.items() if value > max(1e-5, 0.1 * worst)}


def _misalignment(rotations, chip, partner, worlds, faces) -> float:
    """The angle (radians, in [-pi/4, pi/4)) by which the partner's edges are turned from
    the chip's about the partner's face normal, for two boxes (edges every 90 degrees)."""
    face_b = faces[1]
    normal = worlds[partner].normals[face_b[0]][face_b[1]]
    u_a = rotations[chip][:, 0] - (rotations[chip][:, 0] @ normal) * normal
    u_b = rotations[partner][:, 0] - (rotations[partner][:, 0] @ normal) * normal
    angle = np.arctan2(normal @ np.cross(u_a, u_b), u_a @ u_b)
    quarter = np.pi / 2
    return float((angle + quarter / 2) % quarter - quarter / 2)


def _violation(row) -> float:
    if row.sense > 0:
        return max(0.0, row.target - row.value)
    if row.sense < 0:
        return max(0.0, row.value - row.target)
    return abs(row.value - row.target)


def _metric(rotations, inertia, weights):
    blocks = []
    for k in range(len(rotations)):
        w = np.zeros((6, 6))
        w[:3, :3] = np.eye(3)
        w[3:, 3:] = TURN_WEIGHT * rotations[k] @ np.diag(inertia[k]) @ rotations[k].T
        blocks.append(2 * weights[k] * w)
    return sparse.block_diag(blocks, format="csc")


def _facing_faces(worlds, chip, partner, contacts, positions, cos_snap):
    """((piece, face) of the chip, (piece, face) of the partner or None for the conveyor)
    that face each other in a surface contact, or None when no pair is within the snap
    angle."""

    rows = np.flatnonzero(
        ((contacts.chip_a == chip) & (contacts.chip_b == partner))
        | ((contacts.chip_a == partner) & (contacts.chip_b == chip))
    )
    centre = contacts.centre_mm[rows[0]]
    if partner == GROUND:
        target_normal, face_b = np.array([0.0, 0.0, 1.0]), None
    else:
        best = None
        other = worlds[partner]
        for p, (normals, offsets) in enumerate(zip(other.normals, other.offsets, strict=True)):
            distance = np.abs(normals @ centre - offsets)
            distance[normals @ (positions[chip] - centre) <= 0] = np.inf
            k = int(np.argmin(distance))
            if best is None or distance[k] < best[0]:
                best = (float(distance[k]), p, k)
        if best is None or not np.isfinite(best[0]):
            return None
        face_b = (best[1], best[2])
        target_normal = other.normals[best[1]][best[2]]
    best = None
    for p, (normals, offsets) in enumerate(
        zip(worlds[chip].normals, worlds[chip].offsets, strict=True)
    ):
        facing = -(normals @ target_normal)
        for k in np.flatnonzero(facing >= cos_snap):
            distance = abs(normals[k] @ centre - offsets[k])
            if best is None or distance < best[0]:
                best = (distance, p, int(k))
    if best is None:
        return None
    return (best[1], best[2]), face_b


def _near_flush(worlds, surface, align, known):
    """(pair, edge of the chip's face, edge of the partner's face) of every aligned
    surface pair whose edges run parallel within the flush distance alongside each other,
    not in ``known``."""
    out = []
    for pair in sorted(align):
        if pair not in surface:
            continue
        (pa, fa), (pb, fb) = surface[pair]
        edges_a = _face_edges(worlds[pair[0]], pa, fa)
        edges_b = _face_edges(worlds[pair[1]], pb, fb)
        normal = worlds[pair[1]].normals[pb][fb]
        for i, (p, q) in enumerate(edges_a):
            for j, (s, t) in enumerate(edges_b):
                value, overlap = _edge_offset(p, q, s, t, normal)
                if abs(value) < _FLUSH_MM and overlap > 0 and (pair, i, j) not in known:
                    out.append((pair, i, j))
    return out


def _near_corners(worlds, surface, align, known):
    """(pair, which face's corner, corner, edge, side) of every corner of a surface pair
    (not aligned) within the flush distance of the other face's edge, alongside it, and
    not in ``known`` (its first four entries)."""

    out = []
    for pair, ((pa, fa), face_b) in sorted(surface.items()):
        if pair[1] == GROUND or pair in align:
            continue
        pb, fb = face_b
        normal = worlds[pair[1]].normals[pb][fb]
        for first, (p1, f1), (p2, f2) in ((0, (pa, fa), (pb, fb)), (1, (pb, fb), (pa, fa))):
            corners = _face_edges(worlds[pair[first]], p1, f1)
            edges = _face_edges(worlds[pair[1 - first]], p2, f2)
            for i, (corner, _) in enumerate(corners):
                for j, (s, t) in enumerate(edges):
                    if (pair, first, i, j) in known:
                        continue
                    length = np.linalg.norm(t - s)
                    edge = (t - s) / length
                    along = (corner - s) @ edge
                    value = np.cross(normal, edge) @ (corner - s)
                    if abs(value) < _FLUSH_MM and 0 < along < length:
                        out.append((pair, first, i, j, 1.0 if value >= 0 else -1.0))
    return out


def _face_edges(world, piece, face):
    """The edges (corner, next corner) of a face, in order round its normal."""
    corners = _face_corners(world, piece, face)
    normal = world.normals[piece][face]
    centre = corners.mean(axis=0)
    e1 = corners[0] - centre
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    # Angles from the first corner in [0, 2 pi): the opposite corner of a rectangle sits
    # at pi, where arctan2 would flip between -pi and pi with the rounding.
    angles = np.arctan2((corners - centre) @ e2, (corners - centre) @ e1) % (2 * np.pi)
    angles[0] = 0.0
    order = np.argsort(angles)
    corners = corners[order]
    return [(corners[k], corners[(k + 1) % len(corners)]) for k in range(len(corners))]


def _edge_offset(p, q, s, t, normal):
    """How far (mm) edge p-q lies from the line of edge s-t across it, in the plane of
    ``normal``, and how long their common stretch is (mm; <= 0: none); inf when they are
    not nearly parallel."""
    edge = (t - s) / np.linalg.norm(t - s)
    along = q - p
    if abs(along @ edge) < np.cos(np.radians(_ALIGN_DEG)) * np.linalg.norm(along):
        return np.inf, 0.0
    across = np.cross(normal, edge)
    value = float(across @ ((p + q) / 2 - s))
    lo_a, hi_a = sorted(((p - s) @ edge, (q - s) @ edge))
    overlap = min(hi_a, float((t - s) @ edge)) - max(lo_a, 0.0)
    return value, overlap


def _face_corners(world, piece, face):
    v = world.vertices[piece]
    on = np.abs(v @ world.normals[piece][face] - world.offsets[piece][face]) < 1e-6
    return v[on]


def _surface_rows(worlds, chip, partner, face_a, face_b):
    """The chip's face corners in the partner's face plane (equalities)."""
    corners = _face_corners(worlds[chip], *face_a)
    if face_b is None:
        normal, offset, other = np.array([0.0, 0.0, 1.0]), 0.0, -1
    else:
        normal = worlds[partner].normals[face_b[0]][face_b[1]]
        offset = worlds[partner].offsets[face_b[0]][face_b[1]]
        other = partner
    out = []
    for x in corners:
        value = float(normal @ x - offset)
        out.append(
            _Row(
                other,
                chip,
                normal,
                x - value * normal,
                x,
                value,
                0,
                0.0,
                _SURFACE_PENALTY,
                (chip, partner),
            )
        )
    return out


def _floor_rows(world, chip, rule):
    up = np.array([0.0, 0.0, 1.0])
    out = []
    target = rule.lower + SLACK_MM
    lowest = None
    for v in world.vertices:
        for x in v:
            z = float(x[2])
            if lowest is None or z < lowest[0]:
                lowest = (z, x)
            if z < rule.lower + REACH_MM:
                out.append(_Row(-1, chip, up, x * [1, 1, 0], x, z, 1, target, _LOWER_PENALTY))
    if rule.upper < np.inf:
        z, x = lowest
        out.append(
            _Row(-1, chip, up, x * [1, 1, 0], x, z, -1, rule.upper - SLACK_MM, _SOFT_PENALTY)
        )
        if rule.parallel:
            edge = [x for v in world.vertices for x in v if x[2] <= z + CORNER_REACH_MM]
            if len(edge) >= 2:
                out += [
                    _Row(-1, chip, up, x * [1, 1, 0], x, float(x[2]), 0, target, _SOFT_PENALTY)
                    for x in edge[:3]
                ]
    return out


def _pair_rows(worlds, a, b, rule, chosen, piece_gaps):
    """Rows of a pair of chips along its separating axes (see :func:`.clearance._near_features`);
    ``piece_gaps``: the pair's entry of :func:`.rigid.batched_axis_gaps`."""
    wa, wb = worlds[a], worlds[b]
    candidates = []
    for pa_i, pb_i, gaps, sides in piece_gaps:
        k = int(np.argmax(gaps))
        kept = chosen.get((a, b, pa_i, pb_i))
        if kept is not None and gaps[kept[0]] >= gaps[k] - 0.003 and sides[kept[0]] == kept[1]:
            k = kept[0]
        chosen[(a, b, pa_i, pb_i)] = (k, bool(sides[k]))
        candidates.append((float(gaps[k]), pa_i, pb_i, k, bool(sides[k])))
    closest = min(candidates)
    out = []
    target = rule.lower + SLACK_MM
    for gap, pa_i, pb_i, k, ahead in candidates:
        nearest = (pa_i, pb_i) == closest[1:3]
        if gap >= rule.lower + REACH_MM and not (nearest and rule.upper < np.inf):
            continue
        axis = separating_axis(wa, wb, pa_i, pb_i, k)
        normal = axis if ahead else -axis  # from a towards b
        va, vb = wa.vertices[pa_i], wb.vertices[pb_i]
        sa, sb = va @ normal, vb @ normal
        top_a, bottom_b = sa.max(), sb.min()
        near_a = np.flatnonzero(sa >= top_a - CORNER_REACH_MM)
        near_b = np.flatnonzero(sb <= bottom_b + CORNER_REACH_MM)
        n_faces_a = len(wa.normals[pa_i])
        n_faces_b = len(wb.normals[pb_i])
        pairs = []
        if k < n_faces_a:  # a's face: its plane against b's corners
            for j in near_b:
                value = float(sb[j] - top_a)
                pairs.append((vb[j] - value * normal, vb[j], value))
        elif k < n_faces_a + n_faces_b:  # b's face against a's corners
            for i in near_a:
                value = float(bottom_b - sa[i])
                pairs.append((va[i], va[i] + value * normal, value))
        else:
            for i in near_a:
                for j in near_b:
                    pairs.append((va[i], vb[j], float(sb[j] - sa[i])))
        out += [
            _Row(a, b, normal, xa, xb, value, 1, target, _LOWER_PENALTY) for xa, xb, value in pairs
        ]
        if not nearest:
            continue
        first = min(pairs, key=lambda p: p[2])
        if rule.upper < np.inf:
            out.append(
                _Row(
                    a,
                    b,
                    normal,
                    first[0],
                    first[1],
                    first[2],
                    -1,
                    rule.upper - SLACK_MM,
                    _SOFT_PENALTY,
                )
            )
        if rule.parallel and len(pairs) >= 2:
            penalty = _TOUCHING_PENALTY if rule.touching else _SOFT_PENALTY
            for xa, xb, value in sorted(pairs, key=lambda p: p[2])[:3]:
                out.append(_Row(a, b, normal, xa, xb, value, 0, target, penalty))
    return out


def _reachable(rows, positions, radius):
    """The rows that a step within the trust region can bring to their bound (equalities
    always). The others add nothing to the programme (no penalty, no active constraint),
    so leaving them out gives the same step, faster: late steps have small trust regions
    and most rows lie far from theirs (reference stack, seed 0: the programmes took 13.1 s
    of the route's 22 s before)."""
    turn_rad = np.sqrt(3) * radius * _STEP_RAD
    move_mm = np.sqrt(3) * radius * _STEP_MM

    def reach(chip, x, turn):
        if chip < 0:
            return 0.0
        return turn_rad if turn else move_mm + turn_rad * float(np.linalg.norm(x - positions[chip]))

    out = []
    for row in rows:
        if row.sense != 0:
            margin = (row.value - row.target) * row.sense
            if margin > 0:
                change = reach(row.a, row.x_a, row.turn) + reach(row.b, row.x_b, row.turn)
                if margin > 1.01 * change + 1e-9:
                    continue
        out.append(row)
    return out


def _qp(rows, total, metric, positions, caps, radius, anchor=True):
    """The step of every chip's motion (6 n,) from the linearised rows, within the trust
    region and within ``caps`` ((6 n,) up, (6 n,) down) of the start; None when the
    programme fails. ``anchor``: the objective is the motion from the start (else the
    step itself)."""
    rows = _reachable(rows, positions, radius)
    n = len(positions)
    m = len(rows)
    dim = 6 * n
    p_matrix = sparse.block_diag([metric, sparse.csc_matrix((m, m))], format="csc")
    anchored = metric @ total if anchor else np.zeros(dim)
    linear = np.concatenate([anchored, [row.penalty for row in rows]])
    # Jacobian rows: d value = n . (dx_b - dx_a), dx = t + w x (x - c).
    a_idx = np.array([row.a for row in rows])
    b_idx = np.array([row.b for row in rows])
    normal = np.array([row.normal for row in rows])
    x_a = np.array([row.x_a for row in rows])
    x_b = np.array([row.x_b for row in rows])
    values = np.array([row.value for row in rows])
    targets = np.array([row.target for row in rows])
    senses = np.array([row.sense for row in rows])
    turn = np.array([row.turn for row in rows])
    row_ids = np.arange(m)
    data, cols, rws = [], [], []
    for sign, idx, x in ((1.0, b_idx, x_b), (-1.0, a_idx, x_a)):
        on = idx >= 0
        arm = np.cross(x[on] - positions[idx[on]], normal[on])
        arm = np.where(turn[on, None], normal[on], arm)
        push = np.where(turn[on, None], 0.0, normal[on])
        data.append(sign * np.hstack([push, arm]).ravel())
        cols.append((6 * idx[on][:, None] + np.arange(6)).ravel())
        rws.append(np.repeat(row_ids[on], 6))
    jac = sparse.csr_matrix(
        (np.concatenate(data), (np.concatenate(rws), np.concatenate(cols))), shape=(m, dim)
    )
    eye = sparse.identity(m, format="csr")
    blocks_a, bounds = [], []
    lo, hi, eq = senses > 0, senses < 0, senses == 0
    # value + J d + s >= target  ->  -J d - s <= value - target
    blocks_a.append(sparse.hstack([-jac[lo], -eye[lo]]))
    bounds.append(values[lo] - targets[lo])
    # value + J d - s <= target  ->  J d - s <= target - value (equalities: both ways)
    sel = hi | eq
    blocks_a.append(sparse.hstack([jac[sel], -eye[sel]]))
    bounds.append(targets[sel] - values[sel])
    blocks_a.append(sparse.hstack([-jac[eq], -eye[eq]]))
    bounds.append(values[eq] - targets[eq])
    blocks_a.append(sparse.hstack([sparse.csr_matrix((m, dim)), -eye]))  # slacks >= 0
    bounds.append(np.zeros(m))
    # The trust region, and no chip further from where the physics left it than its caps
    # (see _motion_caps: a larger motion is not a resolution but a new stack).
    step = radius * np.tile(np.r_[[_STEP_MM] * 3, [_STEP_RAD] * 3], n)
    up_caps, down_caps = caps
    upper = np.maximum(np.minimum(step, up_caps - total), 0.0)
    lower = np.maximum(np.minimum(step, down_caps + total), 0.0)
    box = sparse.hstack([sparse.identity(dim), sparse.csr_matrix((dim, m))])
    blocks_a += [box, -box]
    bounds += [upper, lower]
    a_matrix = sparse.vstack(blocks_a, format="csc")
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(
        sparse.triu(p_matrix, format="csc"),
        linear,
        a_matrix,
        np.concatenate(bounds),
        [clarabel.NonnegativeConeT(a_matrix.shape[0])],
        settings,
    )
    solution = solver.solve()
    if str(solution.status) not in ("Solved", "AlmostSolved"):
        return None
    x = np.asarray(solution.x)
    step, slack = x[:dim], x[dim:]
    # The merit the linearised model predicts at the step (the rows left out have no
    # penalty there), for the trust region's update against the current merit.
    after = 0.5 * float((total + step) @ (metric @ (total + step))) + float(
        np.dot([row.penalty for row in rows], slack)
    )
    return step, after

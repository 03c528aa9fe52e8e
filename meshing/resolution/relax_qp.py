"""One step of the relaxation: its trust region (how far a chip may move), the metric of
rotations against translations, and the quadratic programme solved by Clarabel."""

from __future__ import annotations

import logging

import clarabel
import numpy as np
import scipy.sparse as sparse

from chipstack.meshing.resolution.relax_settings import (
    _STEP_MM,
    _STEP_RAD,
)
from chipstack.meshing.resolution.rigid import (
    MAX_MOVE_MM,
    MAX_TURN_RAD,
    TURN_WEIGHT,
)

log = logging.getLogger(__name__)


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


def _metric(rotations, inertia, weights):
    blocks = []
    for k in range(len(rotations)):
        w = np.zeros((6, 6))
        w[:3, :3] = np.eye(3)
        w[3:, 3:] = TURN_WEIGHT * rotations[k] @ np.diag(inertia[k]) @ rotations[k].T
        blocks.append(2 * weights[k] * w)
    return sparse.block_diag(blocks, format="csc")


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

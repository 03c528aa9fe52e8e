"""The smallest rigid motions of a few chips that keep each pair's rule, the others held
(sequential quadratic programming with scipy's SLSQP): the bottom-up route's solver."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import null_space
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from chipstack.meshing.resolution.rigid import (
    CORNER_REACH_MM,
    MAX_MOVE_MM,
    MAX_TURN_RAD,
    REACH_MM,
    SLACK_MM,
    TURN_WEIGHT,
    PlacedChip,
    Rule,
    axis_gaps,
    place_chip,
    separating_axis,
    separation_between,
)

__all__ = ["Mover", "clear_group", "motion_basis"]


def motion_basis(planes: list[np.ndarray]) -> np.ndarray:
    """(6, d) the rigid motions (translation, rotation vector about the centre of mass)
    that keep a plate's faces in every plane whose normal is given: no motion along a
    normal, no turn except about it."""
    rows = []
    for normal in planes:
        helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
        e1 = np.cross(normal, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        rows += [np.r_[normal, 0, 0, 0], np.r_[0, 0, 0, e1], np.r_[0, 0, 0, e2]]
    if not rows:
        return np.eye(6)
    return null_space(np.array(rows), rcond=1e-9)


@dataclass
class Mover:
    """A chip free to move in a clearance solve."""

    pieces: tuple
    inertia: np.ndarray
    rotation: np.ndarray
    position: np.ndarray
    basis: np.ndarray  # (6, d)
    fixed: list  # (placed neighbour's world, Rule) it must keep
    floor: Rule | None  # None: lies in the conveyor's plane

    def place(self, q: np.ndarray) -> PlacedChip:
        rotation, position = self.pose(q)
        return place_chip(self.pieces, rotation, position)

    def pose(self, q: np.ndarray):
        motion = self.basis @ q
        return Rotation.from_rotvec(motion[3:]).as_matrix() @ self.rotation, self.position + motion[
            :3
        ]


def clear_group(movers: list[Mover], pairs: list[tuple[int, int, Rule]]):
    """The smallest motions of a group of chips that keep each pair's :class:`Rule`:
    every chip against its placed neighbours and the conveyor, and the group's chips
    against each other (``pairs``: mover, mover, rule).

    Sequential quadratic programming: at each step every near pair is linearised along its
    separating axis (the axis that separates it best, held fixed while it stays nearly the
    best), every corner near the extreme a constraint of its own, and the smallest
    mass-weighted motion meeting them within a trust region is taken, halved when the
    linearisation overshot. The lower bounds are hard (a step never breaks them once they
    hold); the upper bounds and parallel edges are met where the motions allow.

    Returns every chip's (rotation, position), how many lower bounds did not hold at the
    start, and the worst margin left over them (mm; negative: not cleared)."""
    sizes = [m.basis.shape[1] for m in movers]
    cuts = np.cumsum([0, *sizes])
    metric = np.zeros((cuts[-1], cuts[-1]))
    step_limit, limits = [], []
    for m, lo, hi in zip(movers, cuts[:-1], cuts[1:], strict=True):
        weight = np.zeros((6, 6))
        weight[:3, :3] = np.eye(3)
        weight[3:, 3:] = TURN_WEIGHT * m.rotation @ np.diag(m.inertia) @ m.rotation.T
        metric[lo:hi, lo:hi] = m.basis.T @ weight @ m.basis
        translational = np.abs(m.basis[:3]).sum(axis=0) > np.abs(m.basis[3:]).sum(axis=0)
        step_limit.append(np.where(translational, 0.1, 0.01))  # mm, rad per step
        limits.append(np.where(translational, MAX_MOVE_MM, MAX_TURN_RAD))
    step_limit, limits = np.concatenate(step_limit), np.concatenate(limits)
    spans = list(zip(cuts[:-1], cuts[1:], strict=True))

    def place(q):
        return [m.place(q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)]

    def against(worlds):
        """Per mover, what it must keep its rule with: placed neighbours, then the
        group's chips."""
        out = [list(m.fixed) for m in movers]
        for u, v, rule in pairs:
            out[u].append((worlds[v], rule))
        return out

    def margins(worlds):
        values = []
        for m, world, others in zip(movers, worlds, against(worlds), strict=True):
            values += [separation_between(world, other) - rule.lower for other, rule in others]
            if m.floor is not None:
                lowest = min(float(v[:, 2].min()) for v in world.vertices)
                values.append(lowest - m.floor.lower)
        return np.array(values)

    q = np.zeros(cuts[-1])
    worlds = place(q)
    start = margins(worlds)
    closes = int(np.count_nonzero(start < SLACK_MM))
    if not closes and _soft_violation(worlds, against(worlds), movers) == 0:
        return (
            [m.pose(q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)],
            0,
            float(start.min(initial=np.inf)),
        )
    best_q, best_worst, best_score = q, float(start.min(initial=np.inf)), np.inf
    chosen: dict = {}  # each pair's separating axis, kept while it stays nearly the best
    for _ in range(60):
        others = against(worlds)
        features = []
        for u, (m, world) in enumerate(zip(movers, worlds, strict=True)):
            features += [(u, f) for f in _near_features(world, others[u], m.floor, chosen, u)]
        values = _feature_values(worlds, others, features)
        gradient = np.zeros((len(features), len(q)))
        for k in range(len(q)):
            dq = np.zeros_like(q)
            dq[k] = 1e-6
            moved = place(q + dq)
            gradient[:, k] = (_feature_values(moved, against(moved), features) - values) / 1e-6
        sense = np.array([f[-2] for _, f in features], dtype=float)
        targets = np.array([f[-1] for _, f in features], dtype=float)
        delta = _qp_step(metric, q, gradient, values, sense, targets, step_limit, limits)
        if delta is None:
            break
        # A step is taken when it keeps the cleared group clear, or brings an uncleared
        # one closer to clear; otherwise it is halved (the linearisation overshot).
        current = float(margins(worlds).min(initial=np.inf))
        for _ in range(8):
            trial = place(q + delta)
            worst = float(margins(trial).min(initial=np.inf))
            if worst >= 0 or (current < 0 and worst > current + 1e-9):
                break
            delta = delta / 2
        else:
            break
        q, worlds = q + delta, trial
        score = _soft_violation(worlds, against(worlds), movers) + 1e-3 * float(q @ metric @ q)
        if worst >= 0 and (best_worst < 0 or score < best_score):
            best_q, best_worst, best_score = q, worst, score
        elif best_worst < 0 and worst > best_worst:
            best_q, best_worst, best_score = q, worst, score
        if np.abs(delta).max() < 1e-8:
            break
    if best_worst >= 0:
        # The path to a feasible pose can overshoot: the shortest stretch of the way back
        # that still clears everything is kept.
        for fraction in (0.0, 0.25, 0.5, 0.75):
            trial = margins(place(fraction * best_q))
            if trial.min(initial=np.inf) >= 0:
                best_q, best_worst = fraction * best_q, float(trial.min(initial=np.inf))
                break
    poses = [m.pose(best_q[lo:hi]) for m, (lo, hi) in zip(movers, spans, strict=True)]
    return poses, closes, best_worst


def _soft_violation(worlds, others, movers) -> float:
    """How far the upper bounds are exceeded, summed (mm)."""
    total = 0.0
    for m, world, pairs in zip(movers, worlds, others, strict=True):
        for other, rule in pairs:
            if rule.upper < np.inf:
                total += max(0.0, separation_between(world, other) - rule.upper)
        if m.floor is not None and m.floor.upper < np.inf:
            lowest = min(float(v[:, 2].min()) for v in world.vertices)
            total += max(0.0, lowest - m.floor.upper)
    return total


def _near_features(world, others, floor, chosen, tag):
    """The constraints of one chip at this step, each a tuple ending in (sense, target):
    sense +1, the feature's gap must be at least the target; -1, at most; 0, equal.

    A pair's features: ("pair", neighbour, piece of the chip, piece of the neighbour, axis
    index, side, corner of the chip, corner of the neighbour). Every corner pair near the
    extreme along the pair's separating axis is a lower bound of its own (the gap along
    an axis is a minimum over corners, so no step trades one corner for another); the
    nearest corner pair carries the upper bound; a parallel rule holds the touching edge
    or face's corners at the lower bound. The conveyor's: ("floor", piece, corner).

    A pair keeps the axis ``chosen`` for it before while that axis separates it within
    a few micrometres of the best one: switching between two nearly equal axes at every
    step would make the steps undo each other."""
    features = []
    for n, (other, rule) in enumerate(others):
        candidates = []
        for a, (va, na, ea) in enumerate(
            zip(world.vertices, world.normals, world.edges, strict=True)
        ):
            for b, (vb, nb, eb) in enumerate(
                zip(other.vertices, other.normals, other.edges, strict=True)
            ):
                gaps, sides = axis_gaps(va, na, ea, vb, nb, eb)
                k = int(np.argmax(gaps))
                kept = chosen.get((tag, n, a, b))
                if (
                    kept is not None
                    and gaps[kept[0]] >= gaps[k] - 0.003
                    and sides[kept[0]] == kept[1]
                ):
                    k = kept[0]
                chosen[(tag, n, a, b)] = (k, bool(sides[k]))
                candidates.append((float(gaps[k]), a, b, k, bool(sides[k])))
        closest = min(candidates)
        for gap, a, b, k, ahead in candidates:
            nearest = (a, b) == closest[1:3]
            if gap >= rule.lower + REACH_MM and not (nearest and rule.upper < np.inf):
                continue
            axis = separating_axis(world, other, a, b, k)
            pa, pb = world.vertices[a] @ axis, other.vertices[b] @ axis
            if ahead:
                near_a = np.argsort(-pa)[: int(np.sum(pa >= pa.max() - CORNER_REACH_MM))]
                near_b = np.argsort(pb)[: int(np.sum(pb <= pb.min() + CORNER_REACH_MM))]
            else:
                near_a = np.argsort(pa)[: int(np.sum(pa <= pa.min() + CORNER_REACH_MM))]
                near_b = np.argsort(-pb)[: int(np.sum(pb >= pb.max() - CORNER_REACH_MM))]
            head = ("pair", n, a, b, k, ahead)
            features += [
                (*head, int(i), int(j), 1, rule.lower + SLACK_MM) for i in near_a for j in near_b
            ]
            if not nearest:
                continue
            if rule.upper < np.inf:
                features.append((*head, int(near_a[0]), int(near_b[0]), -1, rule.upper - SLACK_MM))
            if rule.parallel:
                # The side holding the edge (or face) is the one with fewer near corners.
                if len(near_a) <= len(near_b):
                    corners = [(int(i), int(near_b[0])) for i in near_a[:3]]
                else:
                    corners = [(int(near_a[0]), int(j)) for j in near_b[:3]]
                if len(corners) >= 2:
                    features += [(*head, i, j, 0, rule.lower + SLACK_MM) for i, j in corners]
    if floor is not None:
        for a, v in enumerate(world.vertices):
            z = v[:, 2]
            features.extend(
                ("floor", a, int(k), 1, floor.lower + SLACK_MM)
                for k in np.flatnonzero(z < floor.lower + REACH_MM)
            )
        lowest = min(
            (
                (float(v[k, 2]), a, int(k))
                for a, v in enumerate(world.vertices)
                for k in range(len(v))
            )
        )
        if floor.upper < np.inf:
            features.append(("floor", lowest[1], lowest[2], -1, floor.upper - SLACK_MM))
        if floor.parallel:
            v = world.vertices[lowest[1]]
            edge = np.argsort(v[:, 2])[: int(np.sum(v[:, 2] <= lowest[0] + CORNER_REACH_MM))]
            if len(edge) >= 2:
                features += [
                    ("floor", lowest[1], int(k), 0, floor.lower + SLACK_MM) for k in edge[:3]
                ]
    return features


def _feature_values(worlds, others, features) -> np.ndarray:
    """The gap (mm) of every feature (see :func:`_near_features`); each separating axis
    is built once for all the corner pairs along it."""
    axes: dict = {}
    out = np.empty(len(features))
    for row, (u, feature) in enumerate(features):
        world = worlds[u]
        if feature[0] == "floor":
            out[row] = world.vertices[feature[1]][feature[2], 2]
            continue
        _, n, a, b, k, ahead, i, j = feature[:8]
        other = others[u][n][0]
        key = (u, n, a, b, k)
        axis = axes.get(key)
        if axis is None:
            axis = axes[key] = separating_axis(world, other, a, b, k)
        pa = world.vertices[a][i] @ axis
        pb = other.vertices[b][j] @ axis
        out[row] = pb - pa if ahead else pa - pb
    return out


def _linear(kind: str, matrix: np.ndarray, bound: np.ndarray) -> dict:
    """An SLSQP constraint ``matrix @ d - bound`` (>= 0 or == 0)."""
    return {"type": kind, "fun": lambda d: matrix @ d - bound, "jac": lambda d: matrix}


def _qp_step(metric, q, gradient, values, sense, targets, step_limit, limits):
    """The step ``delta`` minimising (q + delta)' M (q + delta) subject to the linearised
    constraints (``sense`` +1: value + gradient @ delta >= target; -1: <=; 0: ==),
    |delta| <= step_limit and |q + delta| <= limits.

    When they cannot all be met, the equalities (parallel edges) are dropped, then the
    upper bounds; when even the lower bounds cannot be met, the step that most reduces
    their worst violation is taken; None when that fails too."""
    lower = np.maximum(-step_limit, -limits - q)
    upper = np.minimum(step_limit, limits - q)
    bounds = list(zip(lower, upper, strict=True))
    rows = {
        "lower": (gradient[sense > 0], targets[sense > 0] - values[sense > 0]),
        "upper": (-gradient[sense < 0], values[sense < 0] - targets[sense < 0]),
    }
    a_eq, b_eq = gradient[sense == 0], targets[sense == 0] - values[sense == 0]
    for kept in (("lower", "upper", "eq"), ("lower", "upper"), ("lower",)):
        if "eq" in kept and not len(a_eq):
            continue
        a_in = np.vstack([rows[k][0] for k in kept if k != "eq"])
        b_in = np.concatenate([rows[k][1] for k in kept if k != "eq"])
        constraints = [_linear("ineq", a_in, b_in)]
        if "eq" in kept:
            constraints.append(_linear("eq", a_eq, b_eq))
        result = minimize(
            lambda d: float((q + d) @ metric @ (q + d)),
            np.zeros_like(q),
            jac=lambda d: 2 * metric @ (q + d),
            constraints=constraints,
            bounds=bounds,
            method="SLSQP",
            options={"maxiter": 100, "ftol": 1e-14},
        )
        if np.all(a_in @ result.x - b_in >= -1e-9) and (
            "eq" not in kept or np.abs(a_eq @ result.x - b_eq).max() < 1e-7
        ):
            return result.x
    # The lower bounds cannot all be met within the trust region: the smallest step that
    # comes closest, one shared slack s >= 0 heavily penalised (a linear programme
    # would jump to a corner of the trust region and wander).
    a_in, b_in = rows["lower"]
    if not len(a_in):
        return None
    dim = len(q)
    result = minimize(
        lambda x: float((q + x[:dim]) @ metric @ (q + x[:dim])) + 1e4 * x[dim] ** 2,
        np.zeros(dim + 1),
        jac=lambda x: np.r_[2 * metric @ (q + x[:dim]), 2e4 * x[dim]],
        constraints=[_linear("ineq", np.hstack([a_in, np.ones((len(a_in), 1))]), b_in)],
        bounds=[*bounds, (0, None)],
        method="SLSQP",
        options={"maxiter": 100, "ftol": 1e-14},
    )
    return result.x[:dim] if np.all(np.isfinite(result.x)) else None

"""The loose press's solver: Incremental Potential Contact (ipctk) between separate
elastic chips and two rigid platens, one quasi-static step at a time.

Each step minimises, over the chips' nodal displacements ``u`` and the top platen's
travel ``w`` (mm, downwards),

    1/2 u'Ku + 1/(2 dt) du'K_eta du + 1/2 eps du'M du + drive(w) + kappa B(x) + D(x)

- ``K``: the chips' elastic stiffness (:mod:`meshing.loose.elements`), assembled once;
  ``K_eta`` the same assembly of a viscosity tensor (Kelvin-Voigt, optional) and ``du``
  the displacement since the step's start.
- ``eps M``: a small proximal term, lumped-volume weighted, against the chips' rigid
  modes: a chip that touches nothing yet has no stiffness against moving, and a static
  Newton step on it is singular. Inertia would do the same, but the press is slow and
  inertia would bias every step's forces; the proximal term is instead re-centred on the
  step's solution until its own force is below the tolerance (a proximal-point
  iteration), so that an accepted step is a static equilibrium.
- ``drive``: the platen travel (a stiff spring pulling ``w`` to the step's target) or a
  nominal pressure (the platen's load times ``w``).
- ``B``: ipctk's log barrier over every pair of surface triangles, edges and vertices
  closer than ``dhat`` (no pairs to declare); its stiffness ``kappa`` starts from
  ipctk's gradient balance and is raised by ipctk's rule when gaps keep shrinking.
- ``D``: lagged Coulomb friction (ipctk's smoothed friction potential, its normal
  forces and bases from the step's start).

Every Newton step is bounded by ipctk's continuous collision detection (additive CCD)
before a backtracking line search on the total energy, so that no accepted state
intersects. The linear systems are sparse symmetric positive definite and solved by an
LDL' factorisation that reuses its analysis while the contacts stay
(:mod:`meshing.loose.linear`); one core per press, so two presses fit two cores.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import ipctk
import numpy as np
import scipy.sparse as sp

from chipstack.meshing.loose.linear import PatternReusingLDL

__all__ = ["Platens", "PressBodies", "PressSettings", "StepResult", "IPCPress", "PressError"]

log = logging.getLogger(__name__)


class PressError(RuntimeError):
    """A press step that does not converge, or a start that already intersects."""


@dataclass(frozen=True)
class Platens:
    """Two flat rigid platens: the conveyor at ``bottom_z`` and the press plate at
    ``top_z`` (mm), both over the rectangle ``xy`` = (x0, x1, y0, y1)."""

    bottom_z: float
    top_z: float
    xy: tuple[float, float, float, float]

    @property
    def area_mm2(self) -> float:
        x0, x1, y0, y1 = self.xy
        return (x1 - x0) * (y1 - y0)


@dataclass(frozen=True, eq=False)
class PressBodies:
    """The chips as separate elastic bodies: nodes (n, 3) mm, bricks (m, 8), the chip
    of every brick, the stiffness (3n, 3n) N/mm, the viscous matrix (same, N s/mm) or
    None, the lumped volume of every node (mm^3) and the outward surface triangles."""

    points: np.ndarray
    cells: np.ndarray
    chip: np.ndarray
    stiffness: sp.csr_matrix
    viscous: sp.csr_matrix | None
    node_volume: np.ndarray
    surface: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def node_chip(self) -> np.ndarray:
        owner = np.full(self.n_nodes, -1)
        owner[self.cells.ravel()] = np.repeat(self.chip, self.cells.shape[1])
        return owner


@dataclass(frozen=True)
class PressSettings:
    """How each step is solved (see the module docstring)."""

    dhat_mm: float = 1e-3
    pressure_scale_mpa: float = 10.0  # local contact pressure held at a tenth of dhat
    friction: float = 0.3
    friction_eps_mm: float = 1e-4  # slip (mm per step) below which friction is smoothed
    proximal: float = 1e-6  # eps relative to the stiffness diagonal's mean per volume
    # Measured on the 24-chip stack's first four steps: 1e-4 mm (a tenth of dhat) gives
    # the platen force of 1e-5 mm to 4 digits in 16 % fewer iterations.
    newton_tol_mm: float = 1e-4
    max_newton: int = 80
    max_proximal_rounds: int = 30
    force_tol: float = 1e-3  # proximal force / platen force at an accepted step
    # ... or below this share of the pressure scale over the platens' area: a chip that
    # floats between neighbours (no force holds it) drifts out of the barrier's reach
    # ever slower, and its proximal force never drops below a share of a platen force
    # that is itself nearly nothing.
    force_floor: float = 1e-7
    drive_stiffness: float = 1e3  # times the stiffness diagonal's largest value
    step_time_s: float = 1.0  # for the viscous term
    weight_n_mm3: float = 0.0  # the chips' weight per volume (density times g)


@dataclass
class StepResult:
    """One accepted step: the platen travel (mm), its force and the conveyor's (N), the
    smallest distance between any two surfaces (mm), the Newton iterations, and the
    chips' displacements (n, 3) mm."""

    travel_mm: float
    force_n: float
    conveyor_force_n: float
    min_distance_mm: float
    newton_iterations: int
    barrier_stiffness: float
    seconds: float
    displacement: np.ndarray = field(repr=False)


class IPCPress:
    """The press of ``bodies`` between ``platens`` (see the module docstring)."""

    def __init__(self, bodies: PressBodies, platens: Platens, settings: PressSettings) -> None:
        self.bodies, self.platens, self.settings = bodies, platens, settings
        n = bodies.n_nodes
        self.n_dof = 3 * n + 1  # the chips' nodes and the top platen's travel
        surface_nodes = np.unique(bodies.surface)
        self.surface_nodes = surface_nodes
        index = np.full(n, -1)
        index[surface_nodes] = np.arange(len(surface_nodes))
        x0, x1, y0, y1 = platens.xy
        quad = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        s = len(surface_nodes)
        platen_points = np.vstack(
            [
                np.column_stack([quad, np.full(4, platens.bottom_z)]),
                np.column_stack([quad, np.full(4, platens.top_z)]),
            ]
        )
        self.rest = np.ascontiguousarray(np.vstack([bodies.points[surface_nodes], platen_points]))
        faces = np.vstack(
            [
                index[bodies.surface],
                s + np.array([[0, 2, 1], [0, 3, 2]]),  # the conveyor, facing up
                s + 4 + np.array([[0, 1, 2], [0, 2, 3]]),  # the press plate, facing down
            ]
        ).astype(np.int32)
        edges = ipctk.edges(np.asfortranarray(faces))
        self.mesh = ipctk.CollisionMesh(
            np.asfortranarray(self.rest), np.asfortranarray(edges), np.asfortranarray(faces)
        )
        self.top_vertices = s + 4 + np.arange(4)
        self.bottom_vertices = s + np.arange(4)
        # x_collision (flat) = rest (flat) + S q.
        rows = (3 * np.arange(s)[:, None] + np.arange(3)).ravel()
        cols = (3 * surface_nodes[:, None] + np.arange(3)).ravel()
        top_rows = 3 * self.top_vertices + 2
        self.select = sp.csr_matrix(
            (
                np.concatenate([np.ones(len(rows)), -np.ones(4)]),
                (np.concatenate([rows, top_rows]), np.concatenate([cols, np.full(4, 3 * n)])),
            ),
            shape=(3 * len(self.rest), self.n_dof),
        )
        diagonal = bodies.stiffness.diagonal()
        self.proximal_weight = np.repeat(
            settings.proximal * diagonal.mean() * bodies.node_volume / bodies.node_volume.mean(),
            3,
        )
        self.drive_stiffness = settings.drive_stiffness * diagonal.max()
        self.platen_proximal = float(self.proximal_weight.sum())
        # Gravity: each node's share of its chips' weight, downwards (N).
        self.gravity = np.zeros(3 * n)
        self.gravity[2::3] = -settings.weight_n_mm3 * bodies.node_volume
        self.weight_n = float(-self.gravity.sum())
        self.barrier = ipctk.BarrierPotential(settings.dhat_mm, 1.0)
        chip_faces = faces[: len(bodies.surface)]
        corners = self.rest[chip_faces]
        area = (
            0.5
            * np.linalg.norm(
                np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
            ).sum()
        )
        self.vertex_area = float(area / s)
        self._init_kappa()
        diag = np.linalg.norm(self.rest.max(axis=0) - self.rest.min(axis=0))
        self.bbox_diagonal = float(diag)
        self.broad_phase = ipctk.HashGrid()
        self.ccd = ipctk.AdditiveCCD()
        self.q = np.zeros(self.n_dof)
        self.friction_potential = ipctk.FrictionPotential(settings.friction_eps_mm)
        self._select_t = sp.csr_matrix(self.select.T)
        self._chips_hessian: dict[bool, sp.csr_matrix] = {}
        self.linear = PatternReusingLDL()
        self.check_start()

    # -- geometry ---------------------------------------------------------------
    def vertices(self, q: np.ndarray) -> np.ndarray:
        """(v, 3) the collision mesh's vertices at ``q``, Fortran-ordered for ipctk."""
        flat = self.rest.ravel() + self.select @ q
        return np.asfortranarray(flat.reshape(-1, 3))

    def check_start(self) -> None:
        v = self.vertices(self.q)
        if ipctk.has_intersections(self.mesh, v):
            raise PressError("loose press: the starting stack intersects (chips overlap)")
        collisions = ipctk.NormalCollisions()
        collisions.build(self.mesh, v, self.settings.dhat_mm)
        d = self.min_distance(collisions, v)
        if not d > 0:
            raise PressError("loose press: two surfaces touch at the start (distance 0)")

    def min_distance(self, collisions, v) -> float:
        if collisions.empty():
            return float(self.settings.dhat_mm)
        return float(np.sqrt(max(collisions.compute_minimum_distance(self.mesh, v), 0.0)))

    # -- energy -------------------------------------------------------------------
    def _elastic(self, q, start):
        u = q[:-1]
        du = u - start[:-1]
        k = self.bodies.stiffness
        grad = k @ u + self.proximal_weight * du - self.gravity
        energy = 0.5 * u @ (k @ u) + 0.5 * du @ (self.proximal_weight * du) - self.gravity @ u
        if self.bodies.viscous is not None:
            rate = self.bodies.viscous @ du / self.settings.step_time_s
            grad = grad + rate
            energy += 0.5 * du @ rate
        return energy, grad

    def _drive(self, w, w_centre, target, load):
        """The platen's drive: a stiff spring to the target travel, or the load (N) and
        a proximal term like the chips' (the platen touches nothing at first)."""
        if load is None:
            k = self.drive_stiffness
            return 0.5 * k * (w - target) ** 2, k * (w - target)
        k = self.platen_proximal
        return -load * w + 0.5 * k * (w - w_centre) ** 2, -load + k * (w - w_centre)

    def _contact(self, v, collisions, friction, v_start, derivatives: bool):
        """Barrier and friction on the collision vertices: energy, and when asked its
        gradient and PSD-projected Hessian (on the collision vertices' dofs)."""
        energy = self.kappa * self.barrier(collisions, self.mesh, v)
        slip = np.asfortranarray(v - v_start)
        if friction is not None:
            energy += self.friction_potential(friction, self.mesh, slip)
        if not derivatives:
            return energy, None, None
        grad = self.kappa * self.barrier.gradient(collisions, self.mesh, v)
        hess = self.kappa * self.barrier.hessian(
            collisions, self.mesh, v, ipctk.PSDProjectionMethod.CLAMP
        )
        if friction is not None:
            grad = grad + self.friction_potential.gradient(friction, self.mesh, slip)
            hess = hess + self.friction_potential.hessian(
                friction, self.mesh, slip, ipctk.PSDProjectionMethod.CLAMP
            )
        return energy, grad, hess

    def _collisions(self, v):
        collisions = ipctk.NormalCollisions()
        collisions.build(self.mesh, v, self.settings.dhat_mm)
        return collisions

    def energy(self, q, start, target, load, friction, v_start):
        """The step's total energy at ``q``, with the collision vertices and the
        collisions it was evaluated on (the line search keeps the accepted ones)."""
        v = self.vertices(q)
        collisions = self._collisions(v)
        e_el, _ = self._elastic(q, start)
        e_dr, _ = self._drive(q[-1], start[-1], target, load)
        e_ct, _, _ = self._contact(v, collisions, friction, v_start, False)
        return e_el + e_dr + e_ct, v, collisions

    # -- a step ---------------------------------------------------------------------
    def _init_kappa(self) -> None:
        """The barrier stiffness that holds the pressure scale at a gap of a tenth of
        ``dhat`` on a surface vertex of mean area; ipctk's rule raises it (up to a
        thousand times) when gaps still shrink below a thousandth of ``dhat``."""
        s = self.settings
        d = 0.1 * s.dhat_mm
        slope = abs(2 * d * ipctk.barrier_first_derivative(d * d, s.dhat_mm**2))
        self.kappa = s.pressure_scale_mpa * self.vertex_area / slope
        self.kappa_max = 1e3 * self.kappa

    def step(
        self, target: float, load: float | None = None, guess: np.ndarray | None = None
    ) -> StepResult:
        """Solve one step: the platen driven to travel ``target`` (mm), or under the
        force ``load`` (N) when given. Raises :class:`PressError` when it does not
        converge (the state is then left at the step's start).

        guess: a predicted change of the state over the step (the last step's, scaled),
        where Newton starts, as far along it as is collision-free."""
        started = time.perf_counter()
        s = self.settings
        q_begin = self.q.copy()
        v_start = self.vertices(q_begin)
        collisions = self._collisions(v_start)
        friction = self._lagged_friction(v_start, collisions)
        q = q_begin.copy()
        if guess is not None and np.abs(guess).max() > 0:
            q = q + self._collision_free(q, guess) * guess
        centre = q_begin.copy()
        iterations = 0
        previous_distance = self.min_distance(collisions, v_start)
        # Accelerated proximal point (Gueler's, with O'Donoghue and Candes's restart): the
        # next centre is extrapolated along the rounds' motion, so a chip drifting to its
        # support gets there in the square root of the rounds; the momentum restarts when
        # the proximal force grows. Only the accepted round's force matters: it bounds how
        # far the state is from a static equilibrium, wherever its centre was.
        last_round, momentum, last_force = q_begin.copy(), 1.0, np.inf
        for _round in range(s.max_proximal_rounds):
            q, its, previous_distance, v, collisions = self._newton(
                q, centre, target, load, friction, v_start, previous_distance
            )
            iterations += its
            proximal_force = np.abs(self.proximal_weight * (q[:-1] - centre[:-1])).sum()
            force = abs(self.platen_force(q, friction, v_start)[0])
            floor = s.force_floor * s.pressure_scale_mpa * self.platens.area_mm2
            if proximal_force <= max(s.force_tol * max(force, self.weight_n), floor):
                break
            log.debug(
                "proximal round %d: %d iterations, force %.3g N, platen %.3g N",
                _round + 1,
                its,
                proximal_force,
                force,
            )
            if proximal_force > last_force:
                momentum = 1.0
            following = 0.5 * (1 + np.sqrt(1 + 4 * momentum**2))
            centre = q + ((momentum - 1) / following) * (q - last_round)
            last_round, momentum, last_force = q.copy(), following, proximal_force
            # The friction's normal forces and bases lagged at this round's answer, not
            # at the step's start (whose barrier forces, where the start's gaps are a
            # fraction of dhat, are thousands of times the stack's weight and would pin
            # the chips): the slip is still measured from the start. Measured on the
            # 24-chip stack's first four steps: 163 Newton iterations instead of 199.
            friction = self._lagged_friction(v, collisions)
        else:
            log.warning(
                "loose press: the proximal term's force is still %.3g N after %d rounds",
                proximal_force,
                s.max_proximal_rounds,
            )
        self.q = q
        top, bottom = self.platen_force(q, friction, v_start)
        return StepResult(
            travel_mm=float(q[-1]),
            force_n=float(top),
            conveyor_force_n=float(bottom),
            min_distance_mm=self.min_distance(collisions, v),
            newton_iterations=iterations,
            barrier_stiffness=self.kappa,
            seconds=time.perf_counter() - started,
            displacement=q[:-1].reshape(-1, 3).copy(),
        )

    def _lagged_friction(self, v, collisions):
        """ipctk's tangential collisions with their normal forces at ``v``, or None."""
        s = self.settings
        if s.friction <= 0 or collisions.empty() or self.kappa <= 0:
            return None
        friction = ipctk.TangentialCollisions()
        normal = ipctk.BarrierPotential(s.dhat_mm, self.kappa)
        friction.build(self.mesh, v, collisions, normal, s.friction)
        return None if friction.empty() else friction

    def _newton(self, q, centre, target, load, friction, v_start, previous_distance):
        s = self.settings
        v = self.vertices(q)
        collisions = self._collisions(v)
        for iteration in range(1, s.max_newton + 1):
            e_el, g_el = self._elastic(q, centre)
            e_dr, g_dr = self._drive(q[-1], centre[-1], target, load)
            e_ct, g_ct, h_ct = self._contact(v, collisions, friction, v_start, True)
            gradient = np.concatenate([g_el, [g_dr]]) + self.select.T @ g_ct
            hessian = self._hessian(h_ct, load)
            direction = -self._solve(hessian, gradient)
            # The largest collision-free fraction of the step (ipctk's CCD), then
            # backtracking on the energy.
            alpha = self._collision_free(q, direction)
            energy = e_el + e_dr + e_ct
            slope = gradient @ direction
            while alpha > 1e-12:
                trial = q + alpha * direction
                e_trial, v, collisions = self.energy(trial, centre, target, load, friction, v_start)
                if e_trial <= energy + 1e-4 * alpha * slope:
                    break
                alpha *= 0.5
            else:
                raise PressError(
                    f"loose press: the line search failed at travel {q[-1]:.4f} mm "
                    f"(target {target:.4f} mm)"
                )
            q = trial
            distance = self.min_distance(collisions, v)
            if self.kappa > 0:
                self.kappa = ipctk.update_barrier_stiffness(
                    previous_distance**2,
                    distance**2,
                    self.kappa_max,
                    self.kappa,
                    self.bbox_diagonal,
                    1e-3 * s.dhat_mm / self.bbox_diagonal,
                )
            previous_distance = distance
            log.debug(
                "newton %d: alpha %.3g, step %.3g mm, travel %.6f, d_min %.3g, kappa %.3g, "
                "energy %.6g",
                iteration,
                alpha,
                np.abs(alpha * direction).max(),
                q[-1],
                distance,
                self.kappa,
                energy,
            )
            # The full Newton step, not the one taken: a step the CCD cut short is no
            # sign of convergence.
            if np.abs(direction).max() < s.newton_tol_mm:
                return q, iteration, previous_distance, v, collisions
        raise PressError(
            f"loose press: no convergence in {s.max_newton} Newton iterations at travel "
            f"{q[-1]:.4f} mm (target {target:.4f} mm)"
        )

    def _collision_free(self, q: np.ndarray, direction: np.ndarray) -> float:
        """The largest fraction (at most 1) of ``direction`` from ``q`` along which no
        two surfaces meet (ipctk's additive CCD)."""
        stepsize = ipctk.compute_collision_free_stepsize(
            self.mesh,
            self.vertices(q),
            self.vertices(q + direction),
            broad_phase=self.broad_phase,
            narrow_phase_ccd=self.ccd,
        )
        return min(1.0, stepsize)

    def _hessian(self, h_contact, load) -> sp.csr_matrix:
        """The step's Hessian: the chips' and the drive's (the same at every Newton
        iteration, built once per drive) plus the contact's."""
        driven = load is None
        chips = self._chips_hessian.get(driven)
        if chips is None:
            blocks = self.bodies.stiffness + sp.diags(self.proximal_weight)
            if self.bodies.viscous is not None:
                blocks = blocks + self.bodies.viscous / self.settings.step_time_s
            drive = self.drive_stiffness if driven else self.platen_proximal
            chips = sp.block_diag([blocks, sp.csr_matrix([[drive]])], format="csr")
            self._chips_hessian[driven] = chips
        return (chips + self._select_t @ h_contact @ self.select).tocsr()

    def _solve(self, matrix, rhs) -> np.ndarray:
        return self.linear.solve(matrix, rhs)

    # -- results --------------------------------------------------------------------
    def platen_force(self, q, friction=None, v_start=None) -> tuple[float, float]:
        """(press plate, conveyor) contact forces (N, pressing: positive) at ``q``."""
        v = self.vertices(q)
        collisions = self._collisions(v)
        if collisions.empty() or self.kappa == 0.0:
            return 0.0, 0.0
        grad = self.kappa * self.barrier.gradient(collisions, self.mesh, v).reshape(-1, 3)
        top = -grad[self.top_vertices, 2].sum()
        bottom = grad[self.bottom_vertices, 2].sum()
        return float(top), float(bottom)

    def contact_vertices(self, q, within_mm: float | None = None):
        """The collisions at ``q`` closer than ``within_mm`` (default dhat): (surface
        vertex, face's vertices) of every face-vertex pair, for contact areas."""
        v = self.vertices(q)
        collisions = ipctk.NormalCollisions()
        collisions.build(self.mesh, v, within_mm or self.settings.dhat_mm)
        # ipctk hands out a new list at every access of fv_collisions: read it once.
        pairs = [(c.vertex_id, c.face_id) for c in collisions.fv_collisions]
        return np.array(pairs, dtype=np.int64).reshape(-1, 2)

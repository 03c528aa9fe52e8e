"""Air drag, lift, added-mass torque and rotational damping on chips in flight (the
quasi-steady model of a falling plate)."""

from __future__ import annotations

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.packing.effects.base import AIR_DENSITY_G_MM3, Effect, FlightState

# Quasi-steady coefficients of a falling plate (Andersen, Pesavento & Wang 2005).
_DRAG_A, _DRAG_B, _LIFT_CT = 1.4, 1.0, 1.2


class AirDrag(Effect):
    name = "air_drag"
    parameter = "air density over that of still air at 20 C"
    unit = ""
    prior = (0.0, 4.0)
    simulation_cost = 3.2  # its loads, computed every step in flight
    kinds = ("drop", "stack", "container")
    justification = (
        "A plate falling through air feels drag (coefficient 1.4 - cos 2a: 2.4 broadside, "
        "0.4 edge-on), circulatory lift 1.2 sin 2a, the added-mass (Munk) torque that turns it "
        "face-down, and rotational damping: the quasi-steady model of Andersen, Pesavento & "
        "Wang (J. Fluid Mech. 541, 2005). Over 200 mm it costs a 20 mm chip only 2-4 % of its "
        "impact speed but turns a tilted chip by 10-40 deg, so it changes how the chip meets "
        "the floor. Strength 1 is real air; up to 4 covers the 2-D model's uncertainty."
    )

    def acts_per_step(self) -> bool:
        return True

    def loads(self, state: FlightState, strength: float):
        if strength <= 0:
            return None
        rho = AIR_DENSITY_G_MM3 * strength
        normals = _face_normals(state.quaternions)
        v = state.velocities
        speed = np.linalg.norm(v, axis=1)
        area = _plan_areas(state.shapes)
        side = np.sqrt(area)
        vn = np.einsum("ij,ij->i", v, normals)
        sin_a = np.clip(np.abs(vn) / np.maximum(speed, 1e-12), 0.0, 1.0)
        cos_2a = 1.0 - 2.0 * sin_a**2
        sin_2a = 2.0 * sin_a * np.sqrt(1.0 - sin_a**2)
        drag = -0.5 * rho * area * (_DRAG_A - _DRAG_B * cos_2a) * speed
        forces = drag[:, None] * v
        # Lift: the pressure on the face the air meets (along -sign(vn) n), the part of it
        # across the flow.
        push = -np.sign(vn)[:, None] * normals
        across = push - (np.einsum("ij,ij->i", push, v) / np.maximum(speed**2, 1e-12))[:, None] * v
        norm = np.linalg.norm(across, axis=1)
        lift = 0.5 * rho * area * _LIFT_CT * sin_2a * speed**2
        ok = norm > 1e-12
        forces[ok] += (lift[ok] / norm[ok])[:, None] * across[ok]
        # Munk torque (M_a V) x V with added mass only across the plate: that of the disc
        # of equal area, 8/3 rho R^3.
        added = 8.0 / 3.0 * rho * (area / np.pi) ** 1.5
        torques = _cross((added * vn)[:, None] * normals, v)
        # Rotational damping of the plate turning about an in-plane axis: strips moving
        # broadside with drag 2.4, integrated over a square of side a: 2.4/64 rho a^5 w|w|.
        w = state.angular
        w_in_plane = w - np.einsum("ij,ij->i", w, normals)[:, None] * normals
        torques -= (
            (_DRAG_A + _DRAG_B) / 64.0 * rho * side**5 * np.linalg.norm(w_in_plane, axis=1)
        )[:, None] * w_in_plane
        return forces, torques


def _plan_areas(shapes: tuple[ChipShape, ...]) -> np.ndarray:
    """Each chip's outline area (mm^2): computed once when every chip is the same shape
    object (a drop experiment's), as this runs every step in air."""
    first = shapes[0] if shapes else None
    if all(s is first for s in shapes):
        return np.full(len(shapes), first.plan_area_mm2 if first is not None else 0.0)
    return np.array([s.plan_area_mm2 for s in shapes])


def _face_normals(quaternions: np.ndarray) -> np.ndarray:
    """The chips' local z axes in the world frame (k, 3) from quaternions (k, 4) x, y, z,
    w: the third column of the rotation matrix, written out because this runs every
    step of a drop in air and scipy's Rotation costs more than the engine's step."""
    x, y, z, w = quaternions.T
    return np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (k, 3) arrays (np.cross's overhead dominates at k ~ 60)."""
    return np.column_stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ]
    )


AIR_DRAG = AirDrag()

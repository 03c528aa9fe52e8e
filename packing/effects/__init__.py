"""Physical effects the baseline model leaves out, each a small object registered by name.

An effect has one strength parameter with a unit, a prior range (the values the diagnosis
searches), the strength at which it is absent (``neutral``), the scenario kinds it acts on
and a physical justification (the README's "Candidate effects" table is built from them).
It acts through hooks, run for drops and depositions alike by the runner functions
here (:func:`release_spin`, :func:`apply_effect_loads` every step; and for depositions
:func:`shake_settled` after a batch):

* :meth:`Effect.shape` changes the chip (warp, rounded edges);
* :meth:`Effect.contact` changes the contact model (friction, restitution, floor);
* :meth:`Effect.release` adds angular velocity at release;
* :meth:`Effect.loads` gives forces and torques on flying chips (air);
* :meth:`Effect.after_batch` acts on a settled pile (vibration taps);
* :meth:`Effect.contact_loads` pulls touching chips together (cohesion).

Strengths are given as ``{name: value}``; :func:`check_effects` validates such a mapping.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.core.errors import InputError
from chipstack.packing.effect_kinds import EFFECTS
from chipstack.packing.effects.base import ContactModel, Effect, FlightState

__all__ = [
    "EFFECTS",
    "ContactModel",
    "apply_effect_loads",
    "Effect",
    "EffectSetup",
    "FlightState",
    "check_effects",
    "contact_model",
    "release_spin",
    "setup_effects",
    "shake_settled",
    "spins_at_release",
    "shaped",
]


@dataclass(frozen=True)
class EffectSetup:
    """What a set of effect strengths does to a simulation before it starts: the contact
    model, the physics section carrying its friction and restitution, and the effects
    that act at every step."""

    contact: ContactModel
    physics: object  # packing.sections.PhysicsSpec
    per_step: tuple[tuple[Effect, float], ...]


def setup_effects(preset, physics, strengths: Mapping[str, float]) -> EffectSetup:
    """The contact model and per-step effects of checked ``strengths``."""
    model = contact_model(preset, physics)
    for name, value in strengths.items():
        model = EFFECTS.get(name).contact(model, value)
    return EffectSetup(
        contact=model,
        physics=dataclasses.replace(
            physics, friction=model.friction, restitution=model.restitution
        ),
        per_step=tuple(
            (EFFECTS.get(name), value)
            for name, value in strengths.items()
            if EFFECTS.get(name).acts_per_step() and value > 0
        ),
    )


def release_spin(strengths: Mapping[str, float], draws: np.ndarray) -> np.ndarray:
    """Every effect's release hook summed (drops and depositions alike): extra angular
    velocity (n, 3) rad/s from standard normal ``draws`` (n, 3); zeros when no effect of
    ``strengths`` spins a chip as it leaves its holder."""
    spin = np.zeros(np.shape(draws))
    for name, value in strengths.items():
        extra = EFFECTS.get(name).release(draws, value)
        if extra is not None:
            spin += extra
    return spin


def spins_at_release(strengths: Mapping[str, float]) -> bool:
    """Whether any effect of ``strengths`` has a release hook (its draws are needed)."""
    return any(type(EFFECTS.get(name)).release is not Effect.release for name in strengths)


def apply_effect_loads(
    world, chips: list[int], per_step: list[tuple[Effect, float]]
) -> tuple[np.ndarray, np.ndarray] | None:
    """Apply, for the next step, every per-step effect's loads on the moving ``chips``:
    pulls between touching chips, and loads on flying chips. Returns the chips'
    positions (k, 3) mm and velocities (k, 3) mm/s when they were read (an effect with
    flight loads), else None."""
    for effect, value in per_step:
        effect.contact_loads(world, chips, value)
    flying = [(e, v) for e, v in per_step if type(e).loads is not Effect.loads]
    if not flying or not chips:
        return None
    pos, quat, vel, ang = world.kinematics(chips)
    state = FlightState(
        pos,
        quat,
        vel,
        ang,
        tuple(world.shape(c) for c in chips),
        np.array([world.mass_g(c) for c in chips]),
    )
    forces, torques = np.zeros((len(chips), 3)), np.zeros((len(chips), 3))
    for effect, value in flying:
        loads = effect.loads(state, value)
        if loads is not None:
            forces += loads[0]
            torques += loads[1]
    world.apply_loads(chips, forces, torques, pos)
    return pos, vel


def shake_settled(world, strengths: Mapping[str, float], rng, settle_all) -> int:
    """Every after-batch hook (vibration taps) on a settled pile: each effect acts up to
    its ``taps`` times on every chip, and ``settle_all(chips)`` settles the pile again
    after each act that set chips moving (it returns the steps taken). Returns the steps
    summed."""
    steps = 0
    for name, value in strengths.items():
        effect = EFFECTS.get(name)
        for _ in range(getattr(effect, "taps", 1)):
            everyone = list(range(world.n_chips))
            if not effect.after_batch(world, everyone, value, rng):
                break
            steps += settle_all(everyone)
    return steps


def contact_model(preset, physics) -> ContactModel:
    """The baseline contact model of a scenario's physics section."""
    return ContactModel(
        friction=physics.friction if physics.friction >= 0 else preset.friction,
        restitution=physics.restitution if physics.restitution >= 0 else preset.restitution,
    )


def check_effects(strengths: Mapping[str, float], kind: str, key: str = "effects") -> dict:
    """Validated ``{name: strength}``: known names, finite values within the prior ranges,
    effects that act on scenarios of this ``kind``."""
    checked = {}
    for name, value in strengths.items():
        effect = EFFECTS.get(name, key=key)
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{key}.{name}: strength must be a number, got {value!r}") from None
        effect.check(value, f"{key}.{name}")
        if kind not in effect.kinds:
            raise InputError(
                f"{key}.{name}: effect acts on {', '.join(effect.kinds)} scenarios, not {kind!r}"
            )
        checked[name] = value
    return checked


def shaped(shape: ChipShape, strengths: Mapping[str, float]) -> ChipShape:
    """The chip with every shape effect applied (in registry order)."""
    for name in EFFECTS:
        if strengths.get(name):
            shape = EFFECTS.get(name).shape(shape, strengths[name])
    return shape

"""The coefficient of restitution of impacts."""

from __future__ import annotations

from chipstack.packing.effects.base import ContactCoefficient


class Restitution(ContactCoefficient):
    name = "restitution"
    field = "restitution"
    parameter = "coefficient of restitution of impacts"
    unit = ""
    prior = (0.0, 0.8)
    justification = (
        "No measured value exists for these chips; a thin plate loses much of its impact "
        "energy to flexural vibration (low restitution), a stiff corner impact little. It "
        "sets how high and how often a chip bounces, so how far it travels."
    )


RESTITUTION = Restitution()

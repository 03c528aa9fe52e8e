"""The Coulomb friction coefficient of every contact."""

from __future__ import annotations

from chipstack.packing.effects.base import ContactCoefficient


class Friction(ContactCoefficient):
    name = "friction"
    field = "friction"
    parameter = "Coulomb friction coefficient, chip on chip and chip on floor"
    unit = ""
    prior = (0.1, 1.0)
    justification = (
        "The baseline's 0.5 is an estimate (smooth PA6 about 0.3; textured, glass-rich "
        "edges higher; a belt's rubber 0.6-1). Friction decides how far a landed chip "
        "slides and how steep a pile stands."
    )


FRICTION = Friction()

"""A floor that gives under an impact (a belt, a rubber mat)."""

from __future__ import annotations

from chipstack.packing.effects.base import ContactCoefficient


class CompliantFloor(ContactCoefficient):
    name = "compliant_floor"
    field = "floor_compliance_mm_n"
    parameter = "contact compliance of the floor (its deflection per newton)"
    unit = "mm/N"
    prior = (0.0, 2.0)
    justification = (
        "A conveyor belt or a rubber mat gives under an impact; the baseline floor is rigid. "
        "A compliant floor lengthens the impact and absorbs energy (damping ratio 0.3, a "
        "typical rubber), so a chip bounces less and turns less. 1 mm/N lets a 1.4 g chip "
        "arriving at 2 m/s sink 2.3 mm."
    )


COMPLIANT_FLOOR = CompliantFloor()

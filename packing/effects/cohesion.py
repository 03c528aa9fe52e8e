"""A pull between touching chips (sizing, moisture, static)."""

from __future__ import annotations

from chipstack.packing.effects.base import Effect


class Cohesion(Effect):
    name = "cohesion"
    parameter = "pull-off force at each contact point between chips (sizing, moisture, static)"
    unit = "mN"
    prior = (0.0, 20.0)
    kinds = ("stack", "container")
    justification = (
        "Sizing residues, moisture bridges and static charge make fibres and chips stick: a "
        "cohesive pile stands looser and higher. Modelled as a constant pull along the normal "
        "at every contact point between chips; 13 mN is the weight of one 1.36 g chip."
    )

    def acts_per_step(self) -> bool:
        return True

    def contact_loads(self, world, chips: list[int], strength: float) -> None:
        if strength > 0:
            world.pull_contacts(chips, strength * 1e3)  # mN -> g mm/s^2


COHESION = Cohesion()

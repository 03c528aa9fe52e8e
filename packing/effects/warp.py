"""A chip bowed about its width (a cylindrical bend, exact wedge pieces)."""

from __future__ import annotations

import numpy as np

from chipstack.core.chipshape import ChipShape
from chipstack.packing.effects.base import Effect
from chipstack.packing.effects.shaping import clip_x, prism_outline, shape_from_pieces


class Warp(Effect):
    name = "warp"
    parameter = "bow of the chip: rise of its ends above its middle"
    unit = "mm"
    prior = (0.0, 3.0)
    simulation_cost = 4.5  # 8 wedge pieces in a compound collision shape
    justification = (
        "Chips cut from a consolidated laminate relax residual stresses and warp, and "
        "reheated chips curl; a bowed chip rocks on landing and rests on its ends. Modelled "
        "as a cylindrical bend about the chip's width, 8 exact wedge pieces; up to 3 mm "
        "over 20 mm."
    )

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        if strength <= 0:
            return shape
        outline, thickness = prism_outline(shape, self.name)
        length = float(np.ptp(outline[:, 0]))
        x0 = float(outline[:, 0].min())
        # Radius of the mid-surface whose arc of `length` (the chip is bent, not stretched)
        # rises `strength` at its ends: R (1 - cos(L / 2R)) = h.
        h = strength
        from scipy.optimize import brentq

        radius = brentq(
            lambda r: r * (1 - np.cos(length / (2 * r))) - h, length / np.pi, 1e9 * length
        )
        cuts = np.linspace(x0, x0 + length, 9)
        pieces = []
        for a, b in zip(cuts[:-1], cuts[1:], strict=False):
            strip = clip_x(outline, a, b)
            corners = np.array(
                [[x, y, z] for x, y in strip for z in (-thickness / 2, thickness / 2)]
            )
            theta = corners[:, 0] / radius
            r = radius - corners[:, 2]
            bent = np.column_stack([r * np.sin(theta), corners[:, 1], radius - r * np.cos(theta)])
            pieces.append(bent)
        return shape_from_pieces(shape, pieces, f"{shape.name} warped {h:.3g}")


WARP = Warp()

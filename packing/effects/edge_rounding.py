"""Rounded edges and corners of a worn chip."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from chipstack.core.chipshape import ChipShape
from chipstack.packing.effects.base import Effect
from chipstack.packing.effects.shaping import inset, prism_outline, shape_from_pieces


class EdgeRounding(Effect):
    name = "edge_rounding"
    parameter = "radius of the rounded edges and corners"
    unit = "mm"
    prior = (0.0, 0.9)
    justification = (
        "Shredding and handling crush and wear a chip's edges: real chips have rounded or "
        "chamfered rims, not the sharp box edges of the model. A round rim rolls instead of "
        "catching, so a chip landing on a corner bounces and slides differently. Up to 0.9 mm "
        "for a 2 mm chip (a fully round rim is 1 mm)."
    )

    def shape(self, shape: ChipShape, strength: float) -> ChipShape:
        if strength <= 0:
            return shape
        outline, thickness = prism_outline(shape, self.name)
        r = min(strength, 0.45 * thickness)
        inner = inset(outline, r)
        half = thickness / 2 - r
        # A sphere of radius r swept over the inner prism's corners: its convex hull is the
        # rounded chip (corners sampled at 10 deg in longitude, 5 latitudes).
        lon = np.radians(np.arange(0, 360, 10))
        lat = np.radians([-90, -45, 0, 45, 90])
        ball = np.array(
            [[np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)] for b in lat for a in lon]
        )
        ball = np.unique(np.round(ball, 12), axis=0) * r
        corners = np.array([[x, y, z] for x, y in inner for z in (-half, half)])
        points = (corners[:, None, :] + ball[None, :, :]).reshape(-1, 3)
        points = points[ConvexHull(points).vertices]
        return shape_from_pieces(shape, [points], f"{shape.name} rounded {r:.3g}")


EDGE_ROUNDING = EdgeRounding()

"""Contact resolution: the settled stack made ready for a conformal mesh.

The physics leaves chips a few hundredths of a millimetre into each other, and faces that
rest on each other a fraction of a degree apart; a conformal mesh cannot take either.
:func:`resolve_contacts` moves every chip by a small rigid motion so that surface contacts
become exactly coplanar and touching and every other pair is cleared by a gap (see
:mod:`.resolve`); :func:`resolve_chips` does it for a crop's chips alone.

The public surface, used by the conformal mesher:

* :func:`resolve_contacts`, :func:`resolve_chips`, :func:`check_settings`,
  :class:`Resolution`, :class:`UnresolvedError`;
* the rigid chips it works on: :func:`convex_pieces` (a shape's convex pieces),
  :func:`place_chip` (placed in the world) and :func:`separation_between` (their
  separating-axis distance, mm), and :func:`separation_mm` of two chips of an
  arrangement.

Inside: :mod:`.rigid` (pieces, separating axes, each pair's rule), :mod:`.relax` (the
global route), :mod:`.bottom_up` (the bottom-up route) with :mod:`.clearance` (its
small-motion solver), :mod:`.snapping` (faces laid on planes, the final check).
"""

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.meshing.resolution.resolve import (
        check_settings,
        resolve_chips,
        resolve_contacts,
        separation_mm,
    )
    from chipstack.meshing.resolution.result import Resolution, UnresolvedError
    from chipstack.meshing.resolution.rigid import convex_pieces, place_chip, separation_between

__all__ = [
    "Resolution",
    "UnresolvedError",
    "check_settings",
    "convex_pieces",
    "place_chip",
    "resolve_chips",
    "resolve_contacts",
    "separation_between",
    "separation_mm",
]

# Imported on first use: the mesh kinds' declarations import this package, and these
# modules bring numpy, scipy and clarabel.
lazy_package(
    __name__,
    {
        "Resolution": "chipstack.meshing.resolution.result",
        "UnresolvedError": "chipstack.meshing.resolution.result",
        "check_settings": "chipstack.meshing.resolution.resolve",
        "convex_pieces": "chipstack.meshing.resolution.rigid",
        "place_chip": "chipstack.meshing.resolution.rigid",
        "resolve_chips": "chipstack.meshing.resolution.resolve",
        "resolve_contacts": "chipstack.meshing.resolution.resolve",
        "separation_between": "chipstack.meshing.resolution.rigid",
        "separation_mm": "chipstack.meshing.resolution.resolve",
    },
)

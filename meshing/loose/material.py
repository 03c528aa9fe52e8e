"""The chips' material in the loose press: a transversely isotropic elastic law in each
chip's ply frame (axes 1 and 2 the twill's warp and weft, 3 its normal), with an
optional Kelvin-Voigt viscosity.

At the press temperature (above the PA6 matrix's melting point, 220 C) the matrix is
molten and the glass twill carries the load. The default figures are estimates for the
paper's material (PA6 with 60 wt % balanced glass twill; 18 GPa tensile and 13 GPa
bending modulus at room temperature, paper section 2.2), each a key of ``[solve]``:

- in-plane modulus, 10 GPa: the fibres alone. 60 wt % glass (2.54 g/cm3) in PA6
  (1.14 g/cm3) is 40 % by volume, half of it in each direction of a balanced twill:
  0.20 x 72 GPa = 14.4 GPa by the rule of mixtures, about 0.7 of it left by the weave's
  crimp (the straightening of the yarns before they stretch).
- through-thickness modulus, 10 MPa, and transverse shear modulus, 1 MPa: a stand-in
  for the molten plies, whose through-thickness response is the fibre bed's compaction
  and whose bending is mostly the plies sliding on each other in the molten matrix
  (an order of magnitude of inter-ply shear in forming studies of molten thermoplastic
  laminates, where stresses of tens of kPa arise at slip rates near 1 mm/s). Bending a
  2 mm chip over a 10 mm span is then carried by shear, not by the fibres' stretch: a
  hot chip drapes into the voids under it.
- in-plane shear modulus, 1 MPa: trellising of the twill in a molten matrix.

These are not measured on the project's chips: the loose press states them in its
summary, and a user who has a rheometer or a bending test at temperature sets the keys.
``material = "cold"`` gives the room-temperature chip, isotropic at 3 GPa (the figure
the project's earlier IPC trials used).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ChipMaterial", "HOT_CHIP", "COLD_CHIP", "isotropic"]


@dataclass(frozen=True)
class ChipMaterial:
    """Transversely isotropic elasticity (MPa) about the chip's normal, and a shear
    viscosity (MPa s, 0: none)."""

    in_plane_mpa: float
    through_thickness_mpa: float
    transverse_shear_mpa: float
    in_plane_shear_mpa: float
    in_plane_poisson: float = 0.1
    transverse_poisson: float = 0.05  # contraction through the thickness under in-plane stress
    viscosity_mpa_s: float = 0.0

    def stiffness(self) -> np.ndarray:
        """(6, 6) MPa, the Voigt stiffness in the ply frame (xx, yy, zz, yz, xz, xy)."""
        ep, et = self.in_plane_mpa, self.through_thickness_mpa
        nu, nut = self.in_plane_poisson, self.transverse_poisson
        compliance = np.zeros((6, 6))
        compliance[0, 0] = compliance[1, 1] = 1 / ep
        compliance[0, 1] = compliance[1, 0] = -nu / ep
        compliance[0, 2] = compliance[2, 0] = compliance[1, 2] = compliance[2, 1] = -nut / ep
        compliance[2, 2] = 1 / et
        compliance[3, 3] = compliance[4, 4] = 1 / self.transverse_shear_mpa
        compliance[5, 5] = 1 / self.in_plane_shear_mpa
        stiffness = np.linalg.inv(compliance)
        if np.linalg.eigvalsh(stiffness).min() <= 0:
            raise ValueError("the chip material's stiffness is not positive definite")
        return stiffness

    def viscosity(self) -> np.ndarray | None:
        """(6, 6) MPa s, an isotropic shear viscosity (no bulk part), or None."""
        if self.viscosity_mpa_s <= 0:
            return None
        eta = self.viscosity_mpa_s
        out = np.zeros((6, 6))
        out[:3, :3] = -2 * eta / 3
        out[np.arange(3), np.arange(3)] += 2 * eta
        out[3:, 3:] = np.eye(3) * eta
        return out


def isotropic(modulus_mpa: float, poisson: float) -> ChipMaterial:
    """An isotropic chip as a :class:`ChipMaterial`."""
    shear = modulus_mpa / (2 * (1 + poisson))
    return ChipMaterial(modulus_mpa, modulus_mpa, shear, shear, poisson, poisson)


HOT_CHIP = ChipMaterial(
    in_plane_mpa=10_000.0,
    through_thickness_mpa=10.0,
    transverse_shear_mpa=1.0,
    in_plane_shear_mpa=1.0,
)
COLD_CHIP = isotropic(3000.0, 0.35)

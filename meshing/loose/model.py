"""The loose press as a solve model: its keys and what it accepts (light: every
command-line start reads it; the work is in :mod:`meshing.loose.press`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from chipstack.core.errors import InputError
from chipstack.core.keys import between, key, one_of
from chipstack.core.lazy import named
from chipstack.core.schema import Parameters
from chipstack.meshing.solve_models import SolveModel

if TYPE_CHECKING:
    from pathlib import Path

    from chipstack.core.stages import StageInputs, StageOutput

__all__ = ["LoosePressKeys", "LoosePress", "LOOSE_PRESS"]


@dataclass(frozen=True)
class LoosePressKeys(Parameters):
    """The loose press's own keys (docs/solve.md, "The loose press")."""

    material: str = key(
        "hot",
        "",
        "`hot`: the chips above the matrix's melting point (glass twill in molten PA6, "
        "transversely isotropic in each chip's ply frame); `cold`: isotropic 3 GPa",
        one_of("hot", "cold"),
    )
    in_plane_modulus_mpa: float = key(
        0.0, "MPa", "the ply's in-plane modulus (0: the material's)", between(0.0, 1e6)
    )
    through_thickness_modulus_mpa: float = key(
        0.0, "MPa", "the ply's through-thickness modulus (0: the material's)", between(0.0, 1e6)
    )
    transverse_shear_mpa: float = key(
        0.0,
        "MPa",
        "the ply's transverse (through-thickness) shear modulus, which governs a hot chip's "
        "bending (0: the material's)",
        between(0.0, 1e6),
    )
    in_plane_shear_mpa: float = key(
        0.0, "MPa", "the ply's in-plane shear modulus (0: the material's)", between(0.0, 1e6)
    )
    poisson: float = key(
        -1.0,
        "",
        "the ply's in-plane Poisson ratio (-1: the material's; 0.35 for cold, 0.1 for hot)",
        between(-1.0, 0.49),
    )
    viscosity_mpa_s: float = key(
        0.0,
        "MPa s",
        "a shear viscosity beside the elasticity (Kelvin-Voigt; 0: none): the press then "
        "depends on its speed",
        between(0.0, 1e6),
    )
    press_speed_mm_s: float = key(
        1.0, "mm/s", "the platen's speed, for the viscosity", between(1e-6, 1e4)
    )
    density_g_cm3: float = key(
        1.7,
        "g/cm^3",
        "the chips' density, for their weight (PA6 with 60 wt % glass: 1.7; 0: no weight); "
        "the weight settles chips that nothing else holds yet",
        between(0.0, 20.0),
    )
    friction: float = key(
        0.3, "", "Coulomb friction between chips and on the platens", between(0.0, 2.0)
    )
    drive: str = key(
        "travel",
        "",
        "`travel`: the platen moves press_fraction of the stack's height in steps (stopping "
        "at target_pressure_mpa); `pressure`: the nominal pressure rises to "
        "target_pressure_mpa in steps",
        one_of("travel", "pressure"),
    )
    target_pressure_mpa: float = key(
        2.0,
        "MPa",
        "the nominal pressure (platen force over the stack's footprint) the press stops at, "
        "or rises to with drive = 'pressure' (0: no stop)",
        between(0.0, 1e3),
    )
    barrier_distance_mm: float = key(
        1e-3,
        "mm",
        "the contact barrier's activation distance: surfaces closer than this repel",
        between(1e-6, 0.1),
    )
    newton_iterations: int = key(
        80, "", "the most Newton iterations a step may take before it is cut", between(5, 10000)
    )
    cutbacks: int = key(
        4, "", "how many times a step that does not converge is halved", between(0, 20)
    )


class LoosePress(SolveModel):
    """Every chip its own elastic body, frictional contact by Incremental Potential
    Contact (ipctk) between all of them and with two rigid platens."""

    name = "loose"
    needs = "the loose stack (mesh.kind = 'loose')"
    parameters = LoosePressKeys
    solver = "ipctk"

    def accepts(self, scenario):
        return any(self.name in kind.solve_models for kind in scenario.mesh.chosen)

    def check(self, scenario):
        params = scenario.solve.params
        if params.drive == "pressure" and params.target_pressure_mpa <= 0:
            raise InputError(
                "solve.target_pressure_mpa: must be positive with solve.drive = 'pressure'"
            )

    def check_run(self, scenario) -> None:
        named("chipstack.meshing.loose.press:require_ipctk")()

    def compute(self, inputs: StageInputs, stage: str) -> Any:
        return named("chipstack.meshing.loose.press:press_loose_stack")(inputs, stage)

    def write(self, result: Any, folder: Path, inputs: StageInputs) -> StageOutput:
        return named("chipstack.meshing.loose.press:write_loose_press")(result, folder, inputs)


LOOSE_PRESS = LoosePress()

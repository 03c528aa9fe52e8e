"""The loose press (issue 71, point 3) against CalculiX on the same mesh: a three-chip
stack pressed with CalculiX's own contact pairs (force against compression within 5 %),
and the stiffness of the pressed stack once its gap has closed against the same chips
bonded (within 10 %); :mod:`meshing.loose.reference` writes and runs the decks.

The stack: chips A and B (10 x 10 mm) side by side on the conveyor 1 mm apart, B 0.02 mm
thinner than A (2 mm), and chip C (10 x 10 x 2 mm) bridging them, resting on A over
4.5 mm and on B over 4.5 mm across a 0.02 mm gap; cold isotropic chips (3 GPa,
nu = 0.35), Coulomb friction 0.3 everywhere, C3D8I bricks of 1 x 2.5 x 1 mm in both
solvers. C is first carried by A alone, over part of its face; B takes load once the
gap closes, near a travel of 0.02 mm (the stiffness doubles there).

Measured (CalculiX 2.20, penalty 1e6 MPa/mm, stick slope 1e5 MPa/mm): the loose press's
force 0.2 % and 1.6 % above CalculiX's at compressions of 0.0125 and 0.0166 mm; CalculiX
did not converge past the gap's closure (too many cutbacks at a travel of 0.0225 mm,
with friction), so the contact comparison stops at 0.02 mm. The loose press's tangent
stiffness at the last three steps (gap closed) 88.8, 87.5, 88.7 kN/mm against the bonded
stack's 93.6 kN/mm (0.95). The loose press's first two steps are off (its starting
gaps are half the barrier's distance, whose force preloads the stack): not compared.
"""

from __future__ import annotations

import numpy as np
import pytest
from parts import needs

from chipstack.meshing.loose.ipc import IPCPress, PressSettings
from chipstack.meshing.loose.material import isotropic
from chipstack.meshing.loose.reference import (
    ContactSettings,
    calculix_bonded,
    calculix_press,
    compression_mm,
    stack_faces,
)
from chipstack.meshing.loose.verify import box_bodies, platens_over

DHAT = 1e-4  # mm: the barrier's reach, a tenth of the tests' usual, so its gap is small
GAP = DHAT / 2
DROP = 0.02  # mm, how much thinner B is than A
FRICTION = 0.3
MATERIAL = isotropic(3000.0, 0.35)
CCX_TRAVEL = 0.02  # mm, in 8 increments: CalculiX's last converged travel


def _bridge(material):
    centres = [[-5.5, 0, 1.0], [5.5, 0, 1.0 - DROP / 2], [0, 0, 3.0 + GAP]]
    halves = [[5, 5, 1.0], [5, 5, 1.0 - DROP / 2], [5, 5, 1.0]]
    bodies = box_bodies(centres, halves, material, [(10, 4, 2)] * 3)
    return bodies, platens_over(bodies, GAP)


@pytest.fixture(scope="module")
def loose():
    """The loose press's steps: (travel, compression, force) rows (mm, mm, N)."""
    bodies, platens = _bridge(MATERIAL)
    faces = stack_faces(bodies, platens, 0.04)
    assert faces.pairs == [(0, 2), (1, 2)]
    assert faces.on_conveyor == [0, 1] and faces.under_plate == [2]
    press = IPCPress(
        bodies, platens, PressSettings(dhat_mm=DHAT, friction=FRICTION, pressure_scale_mpa=100.0)
    )
    rows = []
    for travel in np.arange(1, 11) * 0.004:
        result = press.step(travel)
        rows.append((result.travel_mm, compression_mm(faces, result.displacement), result.force_n))
    return np.array(rows)


@needs("ccx")
def test_three_chips_against_calculix_contact_pairs(loose, tmp_path):
    """Force at equal compression within 5 % at every step from 0.012 mm of travel to
    CalculiX's last increment; CalculiX with a 2x stiffer chip misses by far more."""
    bodies, platens = _bridge(MATERIAL)
    settings = ContactSettings(friction=FRICTION, increments=8)
    (tmp_path / "same").mkdir()
    reference = calculix_press(tmp_path / "same", bodies, platens, MATERIAL, CCX_TRAVEL, settings)
    assert reference.travel_mm[-1] == pytest.approx(CCX_TRAVEL)
    assert np.all(np.diff(reference.force_n) > 0) and reference.force_n[-1] > 500.0
    # The conveyor carries what the plate does (the springs hold nearly nothing).
    assert reference.conveyor_force_n == pytest.approx(reference.force_n, rel=1e-3)
    compared = [(c, f) for t, c, f in loose if t > 0.0115 and c <= reference.compression_mm[-1]]
    assert len(compared) >= 2
    for compression, force in compared:
        assert force / reference.force_at(compression) == pytest.approx(1.0, abs=0.05)
    stiff = isotropic(6000.0, 0.35)
    bodies, platens = _bridge(stiff)
    (tmp_path / "stiff").mkdir()
    broken = calculix_press(tmp_path / "stiff", bodies, platens, stiff, CCX_TRAVEL, settings)
    for compression, force in compared:
        assert abs(force / broken.force_at(compression) - 1.0) > 0.3


@needs("ccx")
def test_closed_stack_stiffens_to_the_bonded_stack(loose, tmp_path):
    """The loose press's tangent dF/dc once B carries load (the last three steps) within
    10 % of the bonded stack's stiffness; before the gap closes it is half of it."""
    bodies, platens = _bridge(MATERIAL)
    bonded = calculix_bonded(tmp_path, bodies, platens, MATERIAL)
    assert 5e4 < bonded < 2e5
    tangent = np.diff(loose[:, 2]) / np.diff(loose[:, 1])
    for k in tangent[-3:]:
        assert k / bonded == pytest.approx(1.0, abs=0.10)
    assert tangent[3] / bonded < 0.6  # gap still open: A alone carries C

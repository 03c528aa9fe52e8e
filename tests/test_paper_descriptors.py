"""The paper's descriptor findings on 10-repeat ensembles (section 3, Figs. 7, 10, 12).

Counting convention for contact types (the one the figures below use): a contact is a
touching pair of bodies (two chips, or a chip and the conveyor), counted once; contacts
per chip = contacts of a type / chips in the stack. The other natural convention (every
chip counts each contact it takes part in, so a chip-chip contact counts twice) is also
written to descriptors.json as ``*_per_chip_both_sides``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

pytestmark = pytest.mark.slow

PAPER_CONTACTS = {"point": 1.0, "line": 0.5, "surface": 0.5}  # per chip, Fig. 7 ("about")
# The same ensemble (paper-squares, 10 repeats, seed 0) as recorded in docs/geometry.md,
# with its 95 % intervals: the recorded spread, which a change to the contacts must stay in.
RECORDED = {"point": (1.11, 1.17), "line": (0.49, 0.55), "surface": (0.40, 0.44)}
# Against the paper's values, read off its figure: the largest recorded gap (surface, 0.42
# for 0.5, 16 %) and its interval's half-width (4 %); was 25 %.
TOLERANCE = 0.20


@pytest.fixture(scope="module")
def ensembles(tmp_path_factory):
    root = tmp_path_factory.mktemp("paper")
    out = {}
    for name in ("paper-squares", "paper-rectangles"):
        folder = root / name
        result = run_cli(
            "run",
            name,
            "--to",
            "geometry",
            "--repeats",
            "10",
            "--seed",
            "0",
            "--out",
            str(folder),
            "--quiet",
            "--descriptors",
            "contacts,layers,stack",  # what the findings below read
        )
        assert result.returncode == 0, result.stderr
        out[name] = json.loads((folder / "ensemble.json").read_text())
    result = run_cli(
        "compare",
        str(root / "paper-squares"),
        str(root / "paper-rectangles"),
        "--out",
        str(root / "compare"),
        "--quiet",
    )
    assert result.returncode == 0, result.stderr
    out["compare"] = json.loads((root / "compare" / "compare.json").read_text())
    return out


@pytest.mark.parametrize("kind", ["point", "line", "surface"])
def test_contact_types_per_chip_match_the_paper(ensembles, kind):
    scalars = ensembles["paper-squares"]["descriptors"]["contacts"]["scalars"]
    ours = scalars[f"{kind}_per_chip"]["mean"]
    paper = PAPER_CONTACTS[kind]
    low, high = RECORDED[kind]
    assert low <= ours <= high, f"{kind}: {ours:.3f}, recorded {low} to {high}"
    assert abs(ours - paper) <= TOLERANCE * paper, f"{kind}: {ours:.3f} vs paper {paper}"
    # the other convention is reported too (and is larger: chip-chip contacts count twice)
    assert scalars[f"{kind}_per_chip_both_sides"]["mean"] > ours


def test_layers_14_and_above_are_empty_in_at_least_9_of_10_repeats(ensembles):
    chips = ensembles["paper-squares"]["descriptors"]["layers"]["profiles"]["chips"]
    rows = np.array(chips["values"], dtype=float)
    index = np.array(chips["index"])
    above = rows[:, index >= 14].sum(axis=1) if (index >= 14).any() else np.zeros(len(rows))
    assert len(rows) == 10
    assert np.sum(above == 0) >= 9


def test_rectangle_stacks_are_higher(ensembles):
    """Paper, 3.2.2: the rectangle stack "tends to have a higher height". The mean height
    is the stack's height; it must be significantly higher. The maximum height (one
    chip, an extreme value with a spread of about 2.5 mm over 10 repeats) must be higher
    too, but its significance is not claimed: 10 repeats cannot resolve it (measured: a
    difference of 2.9 mm, p = 0.02, with one realisation of the seeds; 1.4 mm,
    p = 0.22, with the realisation a world rebuilt per batch gives)."""
    scalars = ensembles["compare"]["descriptors"]["stack"]["scalars"]
    for key in ("height_max_mm", "height_mean_mm"):
        assert scalars[key]["difference"] > 0, key  # B (rectangles) minus A (squares)
    assert scalars["height_mean_mm"]["p_permutation"] < 0.05


def test_rectangle_stacks_fill_layers_0_to_4_less(ensembles):
    layers = ensembles["compare"]["descriptors"]["layers"]["profiles"]
    cumulative = {c["index"]: c for c in layers["chips_cumulative"]["comparisons"]}
    assert cumulative[4]["difference"] < 0 and cumulative[4]["p_permutation"] < 0.05
    solid = {c["index"]: c for c in layers["solid_fraction"]["comparisons"]}
    for layer in range(5):
        assert solid[layer]["difference"] < 0, layer
        assert solid[layer]["p_permutation"] < 0.05, layer

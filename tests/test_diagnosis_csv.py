"""Drop observations as spreadsheets write them (issue 54, item 6).

Excel saves "CSV UTF-8" with a byte-order mark and CRLF line endings, and people type
condition names in whatever case. Each variant is read as the plain file is (a name
matching two of the spec's up to case is refused in one line), and ``pipeline diagnose``
on it prints no Python warning and writes no NaN. The data: the first ``MIN_DROPS`` drops
of each condition of the bundled benchmark, the smallest sample the reader accepts.

The warning itself came from the bootstrap, whatever the file's format: halves of five
drops are resampled, and one resample in 625 draws a single drop five times over; it has
no pair of distinct drops, and its within-sample mean distance was 0 / 0 (a
RuntimeWarning, and a NaN passed on into the calibrated adequacy test). The last test
pins that down without a simulation.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_refused, run_cli, tree

from chipstack.diagnosis.spec import MIN_DROPS, load_experiment, read_drop_observations
from chipstack.diagnosis.statistics import mean_within, resample_weights
from chipstack.pipeline.scenario_files import load_scenario

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "drops"
# The cheapest diagnosis the spec allows: few simulated drops, a coarse grid, one effect.
CHEAP = """
[diagnosis]
sim_drops = 20
grid_points = 3
effects = ["friction"]
"""


def _spec(folder: Path, renames: dict[str, str] | None = None) -> Path:
    """The benchmark's three-heights spec in ``folder``, made cheap (conditions renamed)."""
    text = (BENCHMARK / "three-heights.toml").read_text(encoding="utf-8")
    text = text.replace("[measurement]", CHEAP + "\n[measurement]", 1)
    for old, new in (renames or {}).items():
        text = text.replace(f'name = "{old}"', f'name = "{new}"')
    spec = folder / "spec.toml"
    spec.write_text(text, encoding="utf-8")
    return spec


def _lines(drops: int = MIN_DROPS) -> list[str]:
    """The header and the first ``drops`` drops of each condition of the benchmark."""
    header, *rows = (BENCHMARK / "drops.csv").read_text(encoding="utf-8").splitlines()
    seen: dict[str, int] = {}
    kept = [header]
    for row in rows:
        condition = row.split(",", 1)[0]
        seen[condition] = seen.get(condition, 0) + 1
        if seen[condition] <= drops:
            kept.append(row)
    return kept


def _recase(lines: list[str], case) -> list[str]:
    return [lines[0]] + [case(r.split(",", 1)[0]) + "," + r.split(",", 1)[1] for r in lines[1:]]


VARIANTS = {
    "plain": lambda lines: ("\n".join(lines) + "\n").encode(),
    "crlf": lambda lines: ("\r\n".join(lines) + "\r\n").encode(),
    "bom": lambda lines: b"\xef\xbb\xbf" + ("\n".join(lines) + "\n").encode(),
    "bom-crlf": lambda lines: b"\xef\xbb\xbf" + ("\r\n".join(lines) + "\r\n").encode(),
    "cr": lambda lines: ("\r".join(lines) + "\r").encode(),  # old Mac Excel
    "case": lambda lines: ("\n".join(_recase(lines, str.upper)) + "\n").encode(),
}


def _no_nan(text: str):
    def refuse(constant):
        raise AssertionError(f"the report holds {constant}")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("variant", sorted(set(VARIANTS) - {"plain"}))
def test_spreadsheet_variants_read_as_the_plain_file(variant, tmp_path):
    """A byte-order mark, CRLF or lone CR line ends, and condition names differing from the
    spec's only in case give exactly the plain file's drops, by the spec's names."""
    spec = _spec(tmp_path)
    lines = _lines()
    (tmp_path / "drops.csv").write_bytes(VARIANTS["plain"](lines))
    plain = read_drop_observations(load_experiment(spec, load_scenario))
    (tmp_path / "drops.csv").write_bytes(VARIANTS[variant](lines))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read = read_drop_observations(load_experiment(spec, load_scenario))
    assert list(read) == list(plain) == ["h200", "h500", "h1000-yaw30"]
    for name in plain:
        assert read[name].n == MIN_DROPS
        assert np.array_equal(read[name].positions, plain[name].positions)
        assert np.array_equal(read[name].yaw_deg, plain[name].yaw_deg)
        assert np.array_equal(read[name].tilt_deg, plain[name].tilt_deg)


@pytest.mark.parametrize("variant", ["crlf", "bom", "case"])
def test_diagnose_on_a_spreadsheet_csv_prints_no_warning_and_writes_no_nan(variant, tmp_path):
    spec = _spec(tmp_path)
    (tmp_path / "drops.csv").write_bytes(VARIANTS[variant](_lines()))
    out = tmp_path / "out"
    result = run_cli("diagnose", str(spec), "--out", str(out), "--workers", "1", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "Warning" not in result.stderr, result.stderr
    report = _no_nan((out / "diagnosis.json").read_text(encoding="utf-8"))
    assert [(c["name"], c["drops"]) for c in report["conditions"]] == [
        ("h200", MIN_DROPS),
        ("h500", MIN_DROPS),
        ("h1000-yaw30", MIN_DROPS),
    ]
    assert not re.search(r"\bnan\b", (out / "diagnosis.md").read_text(encoding="utf-8"), re.I)


def test_a_condition_name_matching_two_of_the_spec_up_to_case_is_refused(tmp_path):
    """The spec names "Low" and "LOW"; a row's "low" could be either: one line naming the
    file, the line and column, and both candidates."""
    spec = _spec(tmp_path, {"h200": "Low", "h500": "LOW"})
    lines = [r.replace("h200,", "low,", 1).replace("h500,", "LOW,", 1) for r in _lines()]
    (tmp_path / "drops.csv").write_bytes(VARIANTS["crlf"](lines))
    before = tree(tmp_path)
    result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "out"), "--workers", "1")
    assert_refused(result, "drops.csv, line 2, column condition: 'low'", tmp_path, before)
    assert "'LOW', 'Low'" in result.stderr and "Warning" not in result.stderr


def test_too_few_drops_in_a_spreadsheet_csv_is_refused(tmp_path):
    spec = _spec(tmp_path)
    lines = [r for r in _lines() if not r.startswith("h500,")] + [
        r for r in _lines(MIN_DROPS - 1) if r.startswith("h500,")
    ]
    (tmp_path / "drops.csv").write_bytes(VARIANTS["bom-crlf"](_recase(lines, str.upper)))
    before = tree(tmp_path)
    result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "out"), "--workers", "1")
    named = f"condition 'h500' has {MIN_DROPS - 1} drops; at least {MIN_DROPS} are needed"
    assert_refused(result, named, tmp_path, before)
    assert "Warning" not in result.stderr


def test_every_bootstrap_resample_has_a_pair_of_distinct_drops():
    """A resample drawing one drop n times has no pair to average over: it is drawn again
    (two drops: half the resamples would be), and ``mean_within`` refuses a sample or
    resample without a pair instead of dividing 0 by 0."""
    rng = np.random.default_rng(0)
    for n in (2, 3, 5):
        weights = resample_weights(n, 400, rng)
        assert weights.shape == (401, n) and (weights.sum(axis=1) == n).all()
        assert (weights[0] == 1).all() and (weights.max(axis=1) < n).all()
        points = rng.normal(size=(n, 2))
        distances = np.linalg.norm(points[:, None] - points[None], axis=2)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            within = mean_within(distances, weights)
        assert np.isfinite(within).all() and (within > 0).all()
    assert (resample_weights(1, 5, rng) == 1).all()
    with pytest.raises(ValueError, match="fewer than two distinct drops"):
        mean_within(np.zeros((1, 1)), np.ones((1, 1)))
    with pytest.raises(ValueError, match="fewer than two distinct drops"):
        mean_within(np.ones((3, 3)) - np.eye(3), np.array([[1.0, 1.0, 1.0], [0.0, 3.0, 0.0]]))

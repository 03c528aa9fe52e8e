"""Measured figures as data (pipeline/measured.py): recorded as JSON lines, read back,
judged against their targets and rendered into docs/measured.md."""

from __future__ import annotations

import json

import pytest

from chipstack.core.errors import InputError
from chipstack.pipeline.measured import load, met, record, render, write_page


def test_a_recorded_figure_reads_back_with_its_provenance(tmp_path):
    path = record(
        "packing",
        "reference deposition, median of 5",
        3.13,
        "s",
        target="<= 4",
        command="python benchmarks/bench_packing.py",
        headline=True,
        results=tmp_path,
    )
    assert path == tmp_path / "packing" / "measured.jsonl"
    (figure,) = load(tmp_path)
    assert (figure.area, figure.value, figure.unit, figure.target) == ("packing", 3.13, "s", "<= 4")
    assert figure.date.startswith("20") and figure.date.endswith("+00:00")
    assert figure.commit and figure.machine.split()[1] == "cores,"
    raw = json.loads(path.read_text().splitlines()[0])
    assert raw["command"] == "python benchmarks/bench_packing.py"


def test_measuring_again_appends_and_the_page_shows_the_latest_and_the_history(tmp_path):
    for value, date in ((182.2, "2026-11-24T03:57:19+00:00"), (55.0, "2026-11-28T10:00:00+00:00")):
        record(
            "conveyor",
            "3,000 chips",
            value,
            "s",
            target="<= 60",
            date=date,
            commit="abc1234",
            machine_text="2 cores",
            headline=True,
            results=tmp_path,
        )
    record("conveyor", "no target", 7, "", results=tmp_path, date="2026-11-24T00:00:00+00:00")
    assert len(load(tmp_path)) == 3
    page = render(tmp_path)
    latest = page.split("## History")[0]
    assert "| 3,000 chips | 55 s | &le; 60 s | met | 2026-11-28 |" in latest
    assert "182.2 s" not in latest
    history = page.split("## History")[1]
    assert history.index("182.2 s | **not met**") < history.index("55 s | met")
    assert "no target" not in history  # not a headline figure
    assert "| no target | 7 | - | - |" in latest


def test_a_changed_result_file_makes_the_page_stale(tmp_path):
    results, page = tmp_path / "results", tmp_path / "measured.md"
    record("meshing", "voxel mesh at 0.5 mm", 2.4, "s", target="<= 10", results=results)
    assert write_page(results, page) is True
    assert write_page(results, page) is False  # current: nothing to write
    record("meshing", "voxel mesh at 0.5 mm", 12.0, "s", target="<= 10", results=results)
    assert page.read_text() != render(results)
    assert "12 s | &le; 10 s | **not met**" in render(results)


@pytest.mark.parametrize(
    ("value", "target", "verdict"),
    [
        (3.1, "<= 4", True),
        (4.0, "<= 4", True),
        (4.0, "< 4", False),
        (1.84, ">= 1.8", True),
        (1.7, ">= 1.8", False),
        (0, "== 0", True),
        (89.9, "90 to 98", False),
        (98.0, "90 to 98", True),
        (5, "", None),
    ],
)
def test_targets_are_judged(value, target, verdict):
    assert met(value, target) is verdict


@pytest.mark.parametrize(
    ("call", "named"),
    [
        (dict(area="Packing"), "area:"),
        (dict(area="../x"), "area:"),
        (dict(value=float("nan")), "value:"),
        (dict(value="3 s"), "value:"),
        (dict(target="at most 4"), "target:"),
        (dict(name=""), "name:"),
    ],
)
def test_bad_records_are_refused_and_nothing_is_written(tmp_path, call, named):
    arguments = dict(area="packing", name="a figure", value=1.0, unit="s") | call
    with pytest.raises(InputError, match=f"^{named}"):
        record(**arguments, results=tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_broken_line_is_named(tmp_path):
    (tmp_path / "packing").mkdir()
    (tmp_path / "packing" / "measured.jsonl").write_text('{"area": "packing"}\n')
    with pytest.raises(InputError, match=r"measured.jsonl:1: not a measured figure"):
        load(tmp_path)

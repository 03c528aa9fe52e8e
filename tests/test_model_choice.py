"""The amortised model choice of the drop diagnosis (issue 54): its summaries, its
reference table, its probabilities and their checks, on analytic cases and on a small
real design simulated with PyBullet."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from chipstack.diagnosis.choice_checks import expected_calibration_error, smallest_credible_set
from chipstack.diagnosis.model import Condition, DiagnosisSettings, DropData, Experiment
from chipstack.diagnosis.model_choice import build_model_choice
from chipstack.diagnosis.reference_table import NO_EFFECT, MemoryStore, ReferenceTable
from chipstack.diagnosis.summaries import condition_summaries, design_summaries, summary_names
from chipstack.diagnosis.synth import synthesize_drops
from chipstack.packing.drop import DropProtocol
from chipstack.pipeline.scenario_files import load_scenario


def test_expected_calibration_error_of_known_cases():
    rng = np.random.default_rng(0)
    n = 20_000
    # Calibrated: the top class holds 0.8 and is right 80 % of the time.
    truth = np.where(rng.random(n) < 0.8, 0, 1)
    calibrated = np.tile([0.8, 0.2], (n, 1))
    assert expected_calibration_error(calibrated, truth) < 0.01
    # Overconfident: certainty, right half the time.
    coin = rng.integers(0, 2, n)
    assert expected_calibration_error(np.tile([1.0, 0.0], (n, 1)), coin) == pytest.approx(
        0.5, abs=0.02
    )


def test_the_credible_set_is_the_fewest_models_holding_the_level():
    assert smallest_credible_set({"a": 0.96, "b": 0.03, "c": 0.01}) == ["a"]
    assert smallest_credible_set({"a": 0.6, "b": 0.36, "c": 0.04}) == ["a", "b"]
    assert smallest_credible_set({"a": 0.6, "b": 0.3, "c": 0.1}) == ["a", "b", "c"]
    assert smallest_credible_set({"b": 0.3, "a": 0.7}, level=0.5) == ["a"]


def test_summaries_of_a_known_scatter():
    # Four drops on the axes at 10 mm, turned 0 deg, lying flat: an X of order 4 along the
    # release yaw (aniso4_c = 1), no order-2 or -8 sine, zero mean, tilts 0.
    positions = np.array([[10.0, 0.0], [0.0, 10.0], [-10.0, 0.0], [0.0, -10.0]])
    yaw = np.zeros(4)
    tilt = np.zeros(4)
    names = summary_names(True, True)
    values = dict(zip(names, condition_summaries(positions, yaw, tilt, 0.0, 4), strict=True))
    assert len(values) == len(names)
    assert values["r_q50"] == pytest.approx(10.0)
    assert values["aniso4_c"] == pytest.approx(1.0)
    assert values["aniso4_s"] == pytest.approx(0.0, abs=1e-12)
    assert values["aniso2_c"] == pytest.approx(0.0, abs=1e-12)
    assert values["mean_x"] == pytest.approx(0.0) and values["mean_y"] == pytest.approx(0.0)
    assert values["yaw_spread"] == pytest.approx(0.0) and values["tilt_q90"] == 0.0
    assert values["tilt_over_2"] == 0.0
    # Turned by the release yaw, the same scatter reads the same.
    turned = positions @ np.array([[0.0, 1.0], [-1.0, 0.0]]).T * 1.0
    again = condition_summaries(turned, yaw + 90.0, tilt, 90.0, 4)
    assert np.allclose(again[:8], condition_summaries(positions, yaw, tilt, 0.0, 4)[:8])
    # Without angles their columns are left out.
    assert len(condition_summaries(positions, None, None, 0.0, 4)) == len(
        summary_names(False, False)
    )


def _experiment(conditions=((200.0, 0.0), (600.0, 30.0)), effects=(), release_tilt="known"):
    return Experiment(
        name="small",
        kind="drop",
        scenario=load_scenario("single-chip-drop"),
        conditions=tuple(
            Condition(f"h{h:g}", protocol=DropProtocol(height_mm=h, yaw_deg=y))
            for h, y in conditions
        ),
        observations=Path("data.csv"),
        position_sd_mm=0.5,
        angle_sd_deg=0.5,
        settings=DiagnosisSettings(effects=tuple(effects), release_tilt=release_tilt),
    )


def _serial(function, calls):
    return [function(**c) for c in calls]


def test_pools_grow_without_moving_and_round_trip_through_the_store():
    x = _experiment(conditions=((150.0, 0.0),))
    store = MemoryStore()
    table = ReferenceTable(x, [NO_EFFECT, "restitution"], store, pool_drops=6)
    first = table.settings("restitution", 3)
    assert table.settings("restitution", 5)[:3] == first  # more pools move none
    lo, hi = (0.0, 0.8)
    strengths = [s.strength for s in table.settings("restitution", 16)]
    assert all(lo <= v <= hi for v in strengths) and np.ptp(strengths) > 0.6 * (hi - lo)
    assert all(math.isnan(s.strength) for s in table.settings(NO_EFFECT, 2))
    simulated = table.ensure({NO_EFFECT: 1, "restitution": 2}, _serial, lambda m: None)
    assert simulated == 3 * 6
    again = ReferenceTable(x, [NO_EFFECT, "restitution"], store, pool_drops=6)
    again.load()
    assert again.count("restitution") == 2 and again.count(NO_EFFECT) == 1
    assert np.array_equal(again.pools["h150", "restitution"], table.pools["h150", "restitution"])
    assert again.ensure({NO_EFFECT: 1, "restitution": 2}, _serial, lambda m: None) == 0
    # The datasets carry the experiment's measurement noise, drawn per dataset.
    sets = again.datasets({NO_EFFECT: 1}, {"h150": 6}, np.random.default_rng(1))
    noise = sets[0].drops["h150"][:, :2] - again.pools["h150", NO_EFFECT][0][:, :2]
    assert 0.1 < noise.std() < 1.5 and len(sets) == 4  # random subsets of a small pool


def test_a_table_stored_with_longer_pools_serves_shorter_ones_exactly():
    """A drop depends on its pool's seed and its own index alone, so the first 4 drops of
    a stored 6-drop pool are the 4-drop pool: nothing is simulated for it, and a pool
    grown there is simulated at the stored length (the store keeps whole pools); a
    stored pool shorter than needed is simulated again, not cut short."""
    x = _experiment(conditions=((150.0, 0.0),))
    store = MemoryStore()
    long = ReferenceTable(x, ["restitution"], store, pool_drops=6)
    long.ensure({"restitution": 1}, _serial, lambda m: None)
    fresh = ReferenceTable(x, ["restitution"], MemoryStore(), pool_drops=4)
    fresh.ensure({"restitution": 1}, _serial, lambda m: None)
    short = ReferenceTable(x, ["restitution"], store, pool_drops=4)
    short.load()
    assert short.ensure({"restitution": 1}, _serial, lambda m: None) == 0
    assert np.array_equal(short.pools["h150", "restitution"], fresh.pools["h150", "restitution"])
    assert short.ensure({"restitution": 2}, _serial, lambda m: None) == 6  # grown at 6
    assert short.pools["h150", "restitution"].shape == (2, 4, 4)
    whole = ReferenceTable(x, ["restitution"], store, pool_drops=6)
    whole.load()
    assert whole.count("restitution") == 2
    longer = ReferenceTable(x, ["restitution"], store, pool_drops=8)
    longer.load()
    assert longer.count("restitution") == 0  # too short: simulated again


def _drops(x, rows: list[dict]) -> dict[str, DropData]:
    """Synthesised rows as the diagnosis reads them, per condition."""
    return {
        c.name: DropData(
            np.array([[r["x_mm"], r["y_mm"]] for r in rows if r["condition"] == c.name]),
            np.array([r["yaw_deg"] for r in rows if r["condition"] == c.name]),
            np.array([r["tilt_deg"] for r in rows if r["condition"] == c.name]),
        )
        for c in x.conditions
    }


@pytest.mark.slow
def test_the_model_choice_names_a_withheld_effect_and_is_reused(tmp_path):
    """Two conditions x 20 drops, no effect against restitution and friction: the
    design's own cross-validation tells them apart well above chance (1 in 3; a friction
    near the baseline's own is no effect, so a small table's ceiling is about 0.7), the
    probabilities are calibrated,
    synthetic drops made with restitution 0.7 are given restitution with its strength
    in the interval, the learned detection finds them (and not a fresh effect-free
    dataset), and a second call trains nothing and simulates nothing; a model stored
    without the detection's null gets it once."""
    x = _experiment(effects=("restitution", "friction"))
    store = MemoryStore()
    models = [NO_EFFECT, "restitution", "friction"]
    args = (x, {"h200": 20, "h600": 20}, models, 4, True, True, store)
    choice = build_model_choice(*args, _serial, lambda m: None, max_pools=8, seed=0, pool_drops=80)
    checks = choice.checks
    assert checks["accuracy"] > 0.55, checks
    assert checks["expected_calibration_error"] < 0.15, checks
    assert set(checks["strength_interval_coverage"]) == {"restitution", "friction"}
    assert checks["confusion"]["models"] == models
    data = _drops(x, synthesize_drops(x, {"restitution": 0.7}, seed=3, drops=20))
    chosen = choice.choose(design_summaries(data, x, 4, True, True), data)
    assert sum(chosen["probabilities"].values()) == pytest.approx(1.0)
    assert chosen["best_effect"] == "restitution", chosen["probabilities"]
    assert "restitution" in chosen["credible_set"]
    low, high = chosen["strengths"]["restitution"]["strength_ci95"]
    assert low <= 0.7 <= high
    assert chosen["out_of_distribution"]["p_value"] > 0.01
    # Drops a camera scaled by 3 look like nothing in the table.
    scaled = {c: DropData(3.0 * d.positions + 20.0, d.yaw_deg, d.tilt_deg) for c, d in data.items()}
    far = choice.choose(design_summaries(scaled, x, 4, True, True), scaled)
    assert far["out_of_distribution"]["p_value"] < 0.01

    # The learned detection: restitution's drops are unlike the effect-free datasets of
    # the design (their p-value at the floor of its null), a fresh effect-free dataset
    # of the design is not.
    null = choice.no_effect_null
    # Every effect-free dataset of the table, once (the confusion's first row counts them).
    assert len(null) == sum(checks["confusion"]["counts"][0]) and np.all(np.diff(null) >= 0)
    probability = chosen["probabilities"][NO_EFFECT]
    assert choice.detection_p_value(probability) <= 0.05, (probability, null)
    clean = _drops(x, synthesize_drops(x, {}, seed=5, drops=20))
    clean_p = choice.probabilities(design_summaries(clean, x, 4, True, True), clean)[0]
    assert choice.detection_p_value(clean_p) > 0.05, (clean_p, null)

    def refuse(function, calls):
        raise AssertionError("a second diagnosis of the design simulated again")

    again = build_model_choice(*args, refuse, lambda m: None, max_pools=8, seed=0, pool_drops=80)
    assert again.checks == checks
    np.testing.assert_array_equal(again.no_effect_null, null)
    # A model trained before the detection kept its null gets it once, from the same
    # out-of-fold predictions, and keeps it.
    (name,) = [n for n in store.blobs if n.startswith("choice-") and n.endswith(".pkl")]
    del again.no_effect_null
    store.save(name, pickle.dumps(again))
    backfilled = build_model_choice(
        *args, refuse, lambda m: None, max_pools=8, seed=0, pool_drops=80
    )
    np.testing.assert_array_equal(backfilled.no_effect_null, null)
    assert "no_effect_null" in vars(pickle.loads(store.load(name)))


def test_the_learned_detection_p_value_counts_the_null_at_least_as_extreme():
    """(1 + #{null <= t}) / (1 + n): the Monte Carlo p-value, ties counted as extreme."""
    from chipstack.diagnosis.model_choice import ModelChoice

    choice = ModelChoice.__new__(ModelChoice)
    choice.no_effect_null = np.array([0.1, 0.2, 0.2, 0.5, 0.9])
    assert choice.detection_p_value(0.05) == pytest.approx(1 / 6)
    assert choice.detection_p_value(0.2) == pytest.approx(4 / 6)
    assert choice.detection_p_value(1.0) == pytest.approx(1.0)
    choice.no_effect_null = np.zeros(0)
    assert choice.detection_p_value(0.0) == 1.0


@pytest.mark.slow
def test_pipeline_diagnose_names_the_effect_by_model_choice_and_reuses_the_table(tmp_path):
    """``pipeline diagnose`` end to end with the amortised model choice on drops made with
    restitution 0.7: the report names restitution with its probability, the design's
    ceiling in words, and a predictive check; a second diagnosis of the design reuses
    the reference table and the detection's baseline (nothing simulated, no cluster
    started) and gives the same answer."""
    import json

    from conftest import drop_spec, run_cli

    spec = drop_spec(tmp_path, effects=("restitution", "friction"), method="amortised")
    spec.write_text(
        spec.read_text().replace('method = "amortised"', 'method = "amortised"\ntable_pools = 8')
    )
    made = run_cli(
        "synth",
        str(spec),
        "--effect",
        "restitution=0.7",
        "--seed",
        "11",
        "-o",
        str(tmp_path / "data.csv"),
        "--workers",
        "2",
    )
    assert made.returncode == 0, made.stderr
    tables = tmp_path / "tables"
    reports = []
    for name in ("first", "second"):
        out = tmp_path / name
        result = run_cli(
            "diagnose",
            str(spec),
            "--out",
            str(out),
            "--tables",
            str(tables),
            "--workers",
            "2",
            "-v",
        )
        assert result.returncode == 0, result.stderr
        assert "Warning" not in result.stderr
        reports.append(json.loads((out / "diagnosis.json").read_text()))
        simulated_table = "reference table: simulating" in result.stderr
        assert simulated_table == (name == "first"), result.stderr
        # The second simulates nothing at all (the detection's baseline is kept beside
        # the table), so it starts no cluster either.
        assert ("simulating" in result.stderr) == (name == "first"), result.stderr
        assert ("Dask cluster" in result.stderr) == (name == "first"), result.stderr
    first, second = reports
    choice = first["model_choice"]
    assert first["verdict"]["kind"] in ("explained", "partly explained"), first["verdict"]
    assert choice["best_effect"] == "restitution"
    assert sum(choice["probabilities"].values()) == pytest.approx(1.0)
    assert "restitution" in choice["credible_set"]
    # The calibrated check has its reference: two datasets cut from each of the effect's
    # 8 pools (table_pools = 8), so its p-value is (1 + m) / 17 for m of the 16 reference
    # p-values at or below the data's; the verdict "explained" rests on it being at least
    # alpha (0.05, the spec's default). Under the right model it is uniform, so no tighter
    # bound holds for every seed (measured here: 14 / 17 = 0.82); the second diagnosis,
    # reusing the stored references, gives exactly the same.
    check = choice["predictive_check"]
    assert check["reference_datasets"] == 16, check
    steps = check["calibrated_p_value"] * 17
    assert steps == pytest.approx(round(steps), abs=1e-9) and 1 <= round(steps) <= 17, check
    assert check["calibrated_p_value"] >= 0.05, check
    assert second["model_choice"]["predictive_check"] == check
    assert choice["design"]["confusion"]["models"] == ["no effect", "restitution", "friction"]
    text = (tmp_path / "first" / "diagnosis.md").read_text()
    assert "## 2. Which effect" in text and "of the time" in text and "nan" not in text
    # The detection joined the exact test and the learned one.
    detection = first["detection"]
    assert detection["rule"] == "simes" and detection["significant"], detection
    assert detection["p_value"] <= 2 * min(
        detection["exact_p_value"], detection["learned"]["p_value"]
    )
    assert "Detection: p =" in text
    assert second["model_choice"]["probabilities"] == choice["probabilities"]
    assert second["verdict"] == first["verdict"]
    assert any(p.name.startswith("choice-") for p in tables.iterdir())


def test_bad_table_settings_are_refused_in_one_line(tmp_path):
    """A ``--tables`` that is a file, and a ``[diagnosis]`` method or table size out of
    range: exit 2, one line naming it, nothing written."""
    from conftest import assert_refused, drop_spec, run_cli, tree

    spec = drop_spec(tmp_path, effects=("friction",), method="amortised")
    (tmp_path / "data.csv").write_text("condition,drop,x_mm,y_mm\n")
    (tmp_path / "a-file").write_text("")
    before = tree(tmp_path)
    result = run_cli(
        "diagnose", str(spec), "--out", str(tmp_path / "o"), "--tables", str(tmp_path / "a-file")
    )
    assert_refused(result, "--tables", tmp_path, before)
    for text, named in (
        ('method = "amortised"', 'method = "guess"'),
        ('method = "amortised"', 'method = "amortised"\ntable_pools = 2'),
        ('method = "amortised"', 'method = "amortised"\ndetection = "learned"'),
    ):
        spec.write_text(spec.read_text().replace(*((text, named))))
        before = tree(tmp_path)
        result = run_cli("diagnose", str(spec), "--out", str(tmp_path / "o"))
        key = (
            "diagnosis.method"
            if "guess" in named
            else "diagnosis.detection"
            if "detection" in named
            else "diagnosis.table_pools"
        )
        assert_refused(result, key, tmp_path, before)
        spec.write_text(spec.read_text().replace(named, text))


def _section_and_check(probabilities: dict[str, float]) -> tuple[dict, dict]:
    """A model-choice section and predictive check in which everything fits: the check
    passes, the data are in distribution, the effect closes the whole gap."""
    from chipstack.diagnosis.choice_checks import smallest_credible_set

    section = dict(
        probabilities=probabilities,
        most_probable=max(probabilities, key=probabilities.get),
        credible_set=smallest_credible_set(probabilities),
        strengths={"restitution": dict(strength=0.6, strength_ci95=[0.5, 0.7])},
        out_of_distribution=dict(p_value=0.5, distance=1.0),
    )
    check = dict(
        effect="restitution",
        strength=0.6,
        p_value=0.5,
        calibrated_p_value=0.5,
        gap_closed=1.0,
        gap_closed_ci95=[0.8, 1.2],
        where={"flagged": []},
    )
    return section, check


def test_no_effect_most_probable_is_never_explained():
    """A detected gap that the classifier puts with effect-free datasets (here 'no
    effect' 54 %, restitution 34 %) is not explained by the best effect, however well its
    check fits; with the effect most probable the same check explains it."""
    from chipstack.diagnosis.drop_choice import _verdict

    section, check = _section_and_check({NO_EFFECT: 0.54, "restitution": 0.34, "friction": 0.12})
    verdict = _verdict(section, check, {"flagged": []}, 0.05)
    assert verdict["kind"] == "partly explained", verdict
    assert verdict["text"].startswith("The most probable model is no effect (no effect 54 %")
    check["gap_closed_ci95"] = [-0.1, 1.2]
    assert _verdict(section, check, {"flagged": []}, 0.05)["kind"] == "unexplained"
    section, check = _section_and_check({NO_EFFECT: 0.02, "restitution": 0.9, "friction": 0.08})
    assert _verdict(section, check, {"flagged": []}, 0.05)["kind"] == "explained"


def test_an_effect_in_a_set_of_three_or_more_is_not_said_to_explain_the_gap():
    """Everything fits, but the 95 % set holds three models (restitution 56 %, friction,
    no effect): the drops do not single the cause out, so the gap is partly explained and
    the text names the set; with two models in the set the same check explains it."""
    from chipstack.diagnosis.drop_choice import _verdict

    three = {"restitution": 0.56, "friction": 0.3, NO_EFFECT: 0.12, "warp": 0.02}
    section, check = _section_and_check(three)
    assert len(section["credible_set"]) == 3
    verdict = _verdict(section, check, {"flagged": []}, 0.05)
    assert verdict["kind"] == "partly explained", verdict
    assert "do not single it out: the 95 % set holds 3 models" in verdict["text"]
    section, check = _section_and_check({"restitution": 0.7, "friction": 0.28, "warp": 0.02})
    assert len(section["credible_set"]) == 2
    assert _verdict(section, check, {"flagged": []}, 0.05)["kind"] == "explained"


def test_the_simulation_key_follows_only_what_a_drop_simulation_reads():
    """Stored pools are found by the simulation key: a setting no drop reads (the output's,
    the name) leaves it, so adding such a key keeps every table; one a drop reads (the
    physics, the chip, the seed its shape is drawn with) changes it."""
    from dataclasses import replace

    from chipstack.diagnosis.reference_table import simulation_key

    s = load_scenario("single-chip-drop")
    key = simulation_key(s)
    assert len(key) == 16
    distance = s.output.contact_distance_mm
    unread = replace(s, name="other", output=replace(s.output, contact_distance_mm=2 * distance))
    assert simulation_key(unread) == key
    assert simulation_key(replace(s, physics=replace(s.physics, friction=0.3))) != key
    assert simulation_key(replace(s, chip=replace(s.chip, length_mm=25.0))) != key
    assert simulation_key(replace(s, seed=s.seed + 1)) != key


def test_the_simulation_version_names_what_a_drop_simulation_returns(tmp_path):
    """The table's pools are keyed by SIMULATION_VERSION, not by the source's bytes, so a
    refactor of ``packing`` keeps every stored pool; a change that changes a drop must
    raise the version. The drops the version names, simulated again, are those stored for
    it; and the comparison fails on a changed drop (its broken case)."""
    import json

    from chipstack.diagnosis.reference_table import (
        code_version,
        fingerprint_drops,
        write_fingerprint,
    )

    stored = json.loads((Path(__file__).parent / "data" / "drop_fingerprint.json").read_text())
    scenario = load_scenario("single-chip-drop")
    again = fingerprint_drops(scenario)

    def differing(drops: dict) -> list[str]:
        return [
            m
            for m in sorted(set(drops) | set(stored["drops"]))
            if m not in drops
            or m not in stored["drops"]
            or not np.allclose(drops[m], stored["drops"][m], rtol=0, atol=1e-6)
        ]

    changed = differing(again)
    assert stored["version"] == code_version() and not changed, (
        f"the drops of {changed} differ from those stored for simulation version "
        f"{stored['version']} (now {code_version()}): raise SIMULATION_VERSION in "
        "diagnosis/reference_table.py and write tests/data/drop_fingerprint.json again "
        "(reference_table.write_fingerprint)"
    )
    assert len(again) >= 5 and all(np.shape(d) == (3, 4) for d in again.values())
    moved = {m: d for m, d in again.items()}
    moved["friction"] = (np.asarray(moved["friction"]) + [1e-3, 0, 0, 0]).tolist()
    assert differing(moved) == ["friction"]
    written = json.loads(write_fingerprint(scenario, tmp_path / "f.json").read_text())
    assert written == {"version": code_version(), "drops": again}


def _joint_drops(rng, n, together: bool) -> np.ndarray:
    """Drops whose distance and tilt have the same marginals either way: tied together
    (a far slide ends flat, a short one tilted) or independent."""
    far = rng.random(n) < 0.5
    r = np.where(far, rng.uniform(40, 60, n), rng.uniform(2, 6, n))
    tilted = ~far if together else rng.random(n) < 0.5
    tilt = np.where(tilted, rng.uniform(20, 40, n), rng.uniform(0.1, 1.0, n))
    angle = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(angle), r * np.sin(angle), rng.uniform(0, 90, n), tilt])


def test_the_learned_summary_reads_what_single_drops_carry_jointly():
    """Two models with the same distance and tilt marginals, differing only in how the
    two go together: the learned summary's summed log probability favours the true
    model on new datasets of 30 drops (its columns named per condition and overall)."""
    from chipstack.diagnosis.learned_summary import LearnedSummary

    rng = np.random.default_rng(0)
    conditions = [("a", 0.0), ("b", 30.0)]
    train = [{c: _joint_drops(rng, 30, k == 1) for c, _ in conditions} for k in (0, 1) * 40]
    labels = np.array([0, 1] * 40)
    learned = LearnedSummary(conditions, 2, 4, True, True, seed=0).fit(train, labels)
    assert learned.names(["independent", "together"])[-1] == "all:drop_logp_together"
    new = [{c: _joint_drops(rng, 30, k == 1) for c, _ in conditions} for k in (0, 1) * 20]
    summary = learned.transform(new)
    assert summary.shape == (40, 6)
    assert np.allclose(summary[:, 4:], summary[:, 0:2] + summary[:, 2:4])
    favoured = summary[:, 5] > summary[:, 4]  # the overall log probability of "together"
    assert np.array_equal(favoured, np.array([False, True] * 20))

"""Which effect: amortised simulation-based model choice (ABC random forests).

For an experiment's design (its conditions, drops per condition, the angles it records,
its measurement noise, the chip) a reference table of simulated datasets is built
(``diagnosis.reference_table``): "no effect" and every candidate effect, strengths drawn
over each prior, the release tilt a nuisance when it is not known. Each dataset is
summarised (``diagnosis.summaries``, every condition's summaries side by side) and a
random forest learns the model from the summaries (Pudlo et al., Bioinformatics 32, 2016:
reliable ABC model choice via random forests). Its votes are turned into posterior
probabilities by a multinomial logistic map fitted on out-of-fold votes (Dirichlet
calibration, Kull et al., NeurIPS 2019), and everything is checked on itself by
cross-validation grouped by pool (datasets cut from one pool share a strength; splitting
them would flatter the accuracy): the design's accuracy, its confusion, which pairs it
cannot tell apart, the expected calibration error. Each effect's strength has a
quantile-regression interval (gradient boosting, conformalised on out-of-fold residuals
so that 95 % intervals hold 95 % of the table's strengths; Romano et al., NeurIPS 2019),
the release tilt marginalised by being drawn in the table. An out-of-distribution score
says when the data look like none of the simulated datasets: the distance to the nearest
table datasets in whitened summary space, against the same distance of held-out table
datasets.

Training takes seconds to a minute; the trained models are kept in the table store by a
key of the design and the code, so a second diagnosis of the design reuses them.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import pickle
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import sklearn
from scipy.optimize import minimize
from sklearn.decomposition import PCA
from sklearn.ensemble import RandomForestClassifier, RandomForestRegressor
from sklearn.model_selection import StratifiedGroupKFold
from sklearn.neighbors import NearestNeighbors
from sklearn.preprocessing import StandardScaler

from chipstack.diagnosis.choice_checks import CREDIBLE, design_checks, smallest_credible_set
from chipstack.diagnosis.learned_summary import LearnedSummary
from chipstack.diagnosis.model import Experiment
from chipstack.diagnosis.reference_table import (
    NO_EFFECT,
    NUISANCE_TILT_DEG,
    ReferenceTable,
    TableDataset,
    TableStore,
    pool_drops_for,
)
from chipstack.diagnosis.summaries import design_summaries, summary_names
from chipstack.packing.effects import EFFECTS

__all__ = ["MODEL_CHOICE_VERSION", "ModelChoice", "build_model_choice"]

log = logging.getLogger(__name__)

MODEL_CHOICE_VERSION = 5
TREES = 300
CURVE_TREES = 60  # the size curve's forests (a comparison between sizes, not the figure)
FOLDS = 5
# The table grows in rounds of pools per effect until the cross-validated accuracy levels
# off (a gain under LEVEL_OFF from one round to the next), within these bounds.
POOL_ROUNDS = (8, 16, 24, 32, 40, 48)
LEVEL_OFF = 0.01
# Datasets cut from each pool: its disjoint slices, then random subsets of its drops (each
# with its own measurement noise). They share the pool's strength, so they add sampling
# noise for the forest to learn, not settings; folds keep a pool's datasets together.
DATASETS_PER_POOL = 12
OOD_NEIGHBOURS = 10
OOD_COMPONENTS = 20


def _quiet_parallel(function):
    """Run ``function`` without scikit-learn's "delayed should be used with Parallel"
    UserWarning: the forests' thread pools raise it by the thousand when the scikit-learn
    configuration is not propagated to a worker thread (scikit-learn issue 32631), which
    does not change a result; a diagnosis must print no Python warning."""

    @functools.wraps(function)
    def quiet(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.filterwarnings(
                "ignore", message=r"`sklearn\.utils\.parallel\.delayed` should be used"
            )
            return function(*args, **kwargs)

    return quiet


# The calibration map's bounds. A large smoothing s with a power a is a softmax of the votes
# at temperature s / a (log(v + s) = log s + v / s for small v / s), which a forest whose
# votes spread over the models often needs.
POWER_MAX = 2000.0
SMOOTHING_MAX = 100.0


@dataclass
class _Calibrator:
    """Votes to probabilities by temperature scaling (Guo et al., ICML 2017): p is
    proportional to (votes + smoothing) ** power, the two fitted by the log loss of
    out-of-fold votes. A forest's votes are shrunk towards each other (every tree votes
    for a class however sure the split); the power sharpens them, the smoothing keeps a
    class no tree voted for possible. The map is the same for every class and
    increasing, so the most probable model is the most voted one."""

    power: float = 1.0
    smoothing: float = 1e-3

    def apply(self, votes: np.ndarray, classes: int | None = None) -> np.ndarray:
        logits = self.power * np.log(votes + max(self.smoothing, 1e-6))
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        return p / p.sum(axis=1, keepdims=True)

    @classmethod
    def fit(cls, votes: np.ndarray, truth: np.ndarray) -> _Calibrator:
        rows = np.arange(len(truth))

        def loss(params: np.ndarray) -> float:
            p = cls(float(np.exp(params[0])), float(np.exp(params[1]))).apply(votes)
            return float(-np.mean(np.log(np.clip(p[rows, truth], 1e-300, 1.0))))

        # Bounded search: a map clipped after an unbounded search is not the best within
        # the bounds (a power of 200 with a smoothing of 10, clipped to 50 and 1, is a
        # different and much sharper map).
        bounds = [(math.log(0.05), math.log(POWER_MAX)), (math.log(1e-6), math.log(SMOOTHING_MAX))]
        best = minimize(loss, x0=np.log([1.0, 1e-2]), method="Nelder-Mead", bounds=bounds)
        power, smoothing = np.exp(best.x)
        return cls(
            float(np.clip(power, 0.05, POWER_MAX)), float(np.clip(smoothing, 1e-6, SMOOTHING_MAX))
        )


class _QuantileForest:
    """A quantile regression forest (Meinshausen, JMLR 7, 2006): a random forest whose
    leaves keep their training targets, so that a new point's conditional distribution
    is the training targets weighted by how often they share its leaf."""

    def __init__(self, seed: int) -> None:
        self.forest = RandomForestRegressor(
            n_estimators=120, min_samples_leaf=5, max_features=0.33, random_state=seed, n_jobs=-1
        )

    def fit(self, X: np.ndarray, y: np.ndarray) -> _QuantileForest:
        self.forest.fit(X, y)
        self.leaves = self.forest.apply(X)  # (n, trees)
        self.y = np.asarray(y, dtype=float)
        return self

    def quantiles(self, X: np.ndarray, levels: tuple[float, ...]) -> np.ndarray:
        """(m, len(levels)) conditional quantiles."""
        leaves = self.forest.apply(X)  # (m, trees)
        weights = np.zeros((len(X), len(self.y)))
        for t in range(leaves.shape[1]):
            same = self.leaves[:, t][None, :] == leaves[:, t][:, None]
            weights += same / same.sum(axis=1, keepdims=True)
        order = np.argsort(self.y)
        cumulative = np.cumsum(weights[:, order], axis=1) / leaves.shape[1]
        out = np.empty((len(X), len(levels)))
        for k, q in enumerate(levels):
            index = np.minimum((cumulative < q).sum(axis=1), len(self.y) - 1)
            out[:, k] = self.y[order][index]
        return out


_LEVELS = (0.025, 0.5, 0.975)
# Where the posterior-predictive check looks for the strength that fits best.
SPREAD_LEVELS = (0.1, 0.3, 0.5, 0.7, 0.9)


@dataclass
class _IntervalModel:
    """A parameter's median and conformalised 95 % interval from the summaries."""

    forest: _QuantileForest
    margin: float
    bounds: tuple[float, float]
    coverage_out_of_fold: float

    def predict(self, x: np.ndarray) -> tuple[float, float, float]:
        lo_b, hi_b = self.bounds
        low, median, high = self.forest.quantiles(x[None], _LEVELS)[0]
        median = float(np.clip(median, lo_b, hi_b))
        low = float(np.clip(low - self.margin, lo_b, hi_b))
        high = float(np.clip(high + self.margin, lo_b, hi_b))
        return median, min(low, median), max(high, median)


def _fit_interval(X, y, groups, bounds, seed) -> _IntervalModel:
    """A quantile regression forest's 2.5 and 97.5 % quantiles, widened (or narrowed) by
    the conformal margin that makes the out-of-fold intervals hold 95 % of the truths
    (conformalised quantile regression, folds grouped by pool)."""
    scores = np.zeros(len(y))
    for train, test in _group_folds(np.zeros(len(y), dtype=int), groups, seed, folds=3):
        q = _QuantileForest(seed).fit(X[train], y[train]).quantiles(X[test], (0.025, 0.975))
        scores[test] = np.maximum(q[:, 0] - y[test], y[test] - q[:, 1])
    n = len(y)
    level = min(1.0, math.ceil((n + 1) * CREDIBLE) / n)
    margin = float(np.quantile(scores, level))
    return _IntervalModel(
        forest=_QuantileForest(seed).fit(X, y),
        margin=margin,
        bounds=bounds,
        coverage_out_of_fold=float(np.mean(scores <= margin)),
    )


def _group_folds(labels, groups, seed, folds=FOLDS):
    # Every fold needs each class: no more folds than the class with the fewest pools
    # has pools (a small table, or few datasets a pool once the drops are doubled).
    labels, groups = np.asarray(labels), np.asarray(groups)
    fewest = min(len(np.unique(groups[labels == c])) for c in np.unique(labels))
    splits = min(folds, fewest)
    splitter = StratifiedGroupKFold(n_splits=splits, shuffle=True, random_state=seed)
    return list(splitter.split(np.zeros(len(labels)), labels, groups))


@dataclass
class _OutOfDistribution:
    """How far a dataset lies from the table: the mean distance to its nearest table
    datasets in whitened principal components of the summaries, and the same distance of
    every table dataset to the table without its own pool (the null)."""

    scaler: StandardScaler
    pca: PCA
    neighbours: NearestNeighbors
    null: np.ndarray

    @classmethod
    def fit(cls, X: np.ndarray, groups: np.ndarray, seed: int) -> _OutOfDistribution:
        scaler = StandardScaler().fit(X)
        components = max(1, min(OOD_COMPONENTS, X.shape[1], len(X) - 1))
        pca = PCA(n_components=components, whiten=True, random_state=seed)
        Z = pca.fit_transform(scaler.transform(X))
        per_pool = int(np.max(np.unique(groups, return_counts=True)[1]))
        k = min(OOD_NEIGHBOURS, len(X) - per_pool)
        neighbours = NearestNeighbors(n_neighbors=min(len(X), k + per_pool)).fit(Z)
        distance, index = neighbours.kneighbors(Z)
        null = np.empty(len(X))
        for i in range(len(X)):
            other = groups[index[i]] != groups[i]
            null[i] = distance[i][other][:k].mean()
        return cls(scaler, pca, NearestNeighbors(n_neighbors=k).fit(Z), null)

    def p_value(self, x: np.ndarray) -> tuple[float, float]:
        z = self.pca.transform(self.scaler.transform(x[None]))
        distance = float(self.neighbours.kneighbors(z)[0].mean())
        p = (1 + np.sum(self.null >= distance)) / (1 + len(self.null))
        return float(p), distance


@dataclass
class ModelChoice:
    """The trained model choice of one design: ask it with :meth:`choose`."""

    models: list[str]
    feature_names: list[str]
    classifier: RandomForestClassifier
    calibrator: _Calibrator
    strengths: dict[str, _IntervalModel]
    tilts: dict[str, _IntervalModel]
    ood: _OutOfDistribution
    learned: LearnedSummary
    # The posterior probability of "no effect" of every effect-free table dataset, out of
    # fold (forest and calibration map): the null distribution of the learned detection.
    no_effect_null: np.ndarray = field(default_factory=lambda: np.zeros(0))
    checks: dict = field(default_factory=dict)
    key: str = ""  # the design's key in the table store

    def detection_p_value(self, probability_no_effect: float) -> float:
        """The learned detection's p-value of a dataset whose posterior probability of
        "no effect" is ``probability_no_effect``: the share of effect-free table datasets
        (held out of the classifier's training) that look at most as effect-free, a Monte
        Carlo test with the simulation as its null (1 when the design has no effect-free
        datasets)."""
        null = self.no_effect_null
        if len(null) == 0:
            return 1.0
        return float((1 + np.sum(null <= probability_no_effect + 1e-12)) / (1 + len(null)))

    def probabilities(self, x: np.ndarray, drops: dict) -> np.ndarray:
        """Posterior probabilities of the models (in the order of ``models``) for one
        dataset: its hand-made summary vector ``x`` and its drops per condition."""
        features = np.concatenate([x, self.learned.transform([drops])[0]])
        votes = _votes(self.classifier, features[None], len(self.models))
        return self.calibrator.apply(votes, len(self.models))[0]

    @_quiet_parallel
    def choose(self, x: np.ndarray, drops: dict) -> dict:
        """Posterior probabilities, the best effect, the 95 % set, strengths with
        intervals, and the out-of-distribution p-value of one dataset: its summary
        vector ``x`` (:func:`summaries.design_summaries`) and its drops per condition (DropData or
        (n, 4) arrays), which the learned summary reads."""
        if not np.isfinite(x).all():
            raise ValueError("a summary of the observations is not finite")
        p = self.probabilities(x, drops)
        probabilities = {m: float(v) for m, v in zip(self.models, p, strict=True)}
        effects = {m: v for m, v in probabilities.items() if m != NO_EFFECT}
        best = max(effects, key=effects.get) if effects else None
        strengths = {}
        for effect, model in self.strengths.items():
            median, low, high = model.predict(x)
            spread = model.forest.quantiles(x[None], SPREAD_LEVELS)[0]
            strengths[effect] = dict(
                strength=median,
                strength_ci95=[low, high],
                posterior_quantiles={
                    f"{q:g}": float(np.clip(v, *model.bounds))
                    for q, v in zip(SPREAD_LEVELS, spread, strict=True)
                },
            )
        tilts = {}
        for name, model in self.tilts.items():
            median, low, high = model.predict(x)
            tilts[name] = dict(tilt_deg=median, tilt_ci95_deg=[low, high])
        ood_p, distance = self.ood.p_value(x)
        return dict(
            probabilities=probabilities,
            most_probable=max(probabilities, key=probabilities.get),
            best_effect=best,
            credible_set=smallest_credible_set(probabilities),
            strengths=strengths,
            release_tilts=tilts,
            out_of_distribution=dict(p_value=ood_p, distance=distance),
        )


def _votes(classifier: RandomForestClassifier, X: np.ndarray, classes: int) -> np.ndarray:
    out = np.zeros((len(X), classes))
    out[:, classifier.classes_] = classifier.predict_proba(X)
    return out


def _forest(seed: int, trees: int = TREES) -> RandomForestClassifier:
    return RandomForestClassifier(
        n_estimators=trees, min_samples_leaf=1, max_features="sqrt", n_jobs=-1, random_state=seed
    )


def _cross_validated(X, y, groups, classes, seed, trees=TREES):
    """Out-of-fold votes (n, classes) of forests trained on the other folds' pools."""
    votes = np.zeros((len(y), classes))
    for train, test in _group_folds(y, groups, seed):
        forest = _forest(seed, trees).fit(X[train], y[train])
        votes[test] = _votes(forest, X[test], classes)
    return votes


class _Design:
    """The datasets of one design cut from its reference table, summarised."""

    def __init__(self, experiment, table: ReferenceTable, drops, order, has_yaw, has_tilt):
        self.x = experiment
        self.table = table
        self.drops = drops
        self.order = order
        self.has_yaw, self.has_tilt = has_yaw, has_tilt
        self.feature_names = [
            f"{c.name}:{n}" for c in experiment.conditions for n in summary_names(has_yaw, has_tilt)
        ]

    def key(self, counts: dict[str, int]) -> str:
        text = json.dumps(
            dict(
                version=MODEL_CHOICE_VERSION,
                sklearn=sklearn.__version__,
                table=self.table.simulation_key,
                pool_drops=self.table.pool_drops,
                conditions=[
                    [c.protocol.height_mm, c.protocol.yaw_deg, c.protocol.tilt_deg]
                    for c in self.x.conditions
                ],
                release_tilt=self.table.release_tilt,
                drops=[self.drops[c.name] for c in self.x.conditions],
                noise=[self.x.position_sd_mm, self.x.angle_sd_deg],
                angles=[self.has_yaw, self.has_tilt],
                counts=sorted(counts.items()),
                per_pool=DATASETS_PER_POOL,
            ),
            sort_keys=True,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    def learned(self, models: list[str], seed: int) -> LearnedSummary:
        """An untrained learned summary of the design."""
        conditions = [(c.name, c.protocol.yaw_deg) for c in self.x.conditions]
        return LearnedSummary(
            conditions, len(models), self.order, self.has_yaw, self.has_tilt, seed
        )

    def arrays(self, counts: dict[str, int]):
        """The design's datasets cut from the table: hand-made summaries (n, k), model
        labels, pool groups, strengths, release tilts, and the datasets' drops."""
        rng = np.random.default_rng(int(self.key(counts)[:8], 16))
        sets: list[TableDataset] = self.table.datasets(counts, self.drops, rng, DATASETS_PER_POOL)
        models = list(counts)
        X = np.array(
            [
                design_summaries(d.drops, self.x, self.order, self.has_yaw, self.has_tilt)
                for d in sets
            ]
        )
        y = np.array([models.index(d.setting.model) for d in sets])
        groups = np.array([models.index(d.setting.model) * 10_000 + d.setting.index for d in sets])
        strength = np.array([d.setting.strength for d in sets])
        tilt = np.array([d.setting.tilt_deg for d in sets])
        return X, y, groups, strength, tilt, sets


@_quiet_parallel
def build_model_choice(
    experiment: Experiment,
    drops: dict[str, int],
    models: list[str],
    order: int,
    has_yaw: bool,
    has_tilt: bool,
    store: TableStore,
    run_many: Callable[[Callable, list[dict]], list],
    progress: Callable[[str], None],
    max_pools: int = POOL_ROUNDS[-1],
    seed: int = 0,
    pool_drops: int | None = None,
) -> ModelChoice:
    """The trained model choice of the design: from the store when it was trained
    before, else the table grown until the cross-validated accuracy levels off (its
    pools simulated through ``run_many``, kept in ``store``), then trained and checked."""
    pool_drops = pool_drops_for(drops, pool_drops)
    table = ReferenceTable(experiment, models, store, pool_drops)
    design = _Design(experiment, table, drops, order, has_yaw, has_tilt)
    table.load()
    plan_name = f"choice-plan-{design.key({'table_pools': max_pools})}.json"
    plan = store.load(plan_name)
    if plan is not None:  # trained before: the size it chose, and the trained models
        blob = store.load(f"choice-{design.key(json.loads(plan))}.pkl")
        if blob is not None:
            trained = pickle.loads(blob)
            progress(f"model choice: trained before ({trained.checks['datasets']} datasets)")
            if "no_effect_null" not in vars(trained):
                # Trained before the learned detection kept its null: the same out-of-fold
                # predictions again (the folds of the training's seed), kept with it.
                progress("model choice: the learned detection's null (once for this design)")
                counts = json.loads(plan)
                oof = _out_of_fold(
                    design, counts, models, trained.checks.get("seed", seed), progress
                )
                trained.no_effect_null = oof.no_effect_null(models)
                store.save(f"choice-{trained.key}.pkl", pickle.dumps(trained))
            return trained
    effects = [m for m in models if m != NO_EFFECT] or models
    existing = min(table.count(m) for m in effects)
    # The sizes tried: the rounds up to what the table holds (no simulation), then each
    # further round simulated only while the accuracy still gains.
    sizes = sorted({j for j in POOL_ROUNDS if j < max_pools} | {max_pools})
    held = [j for j in sizes if j <= existing]
    sizes = held[-2:] + [j for j in sizes if j > existing]
    curve: list[dict] = []
    chosen = None
    for j in sizes:
        counts = _counts(models, j)
        table.ensure(counts, run_many, progress)
        X, y, groups, _, _, _ = design.arrays(counts)
        # The size curve compares sizes on the hand-made summaries alone (the learned
        # summary's per-drop classifiers would cost a minute per size).
        votes = _cross_validated(X, y, groups, len(models), seed, trees=CURVE_TREES)
        accuracy = float(np.mean(votes.argmax(axis=1) == y))
        curve.append(dict(pools_per_effect=j, datasets=len(y), accuracy=accuracy))
        progress(
            f"model choice: {j} pools per effect, {len(y)} datasets, "
            f"cross-validated accuracy {100 * accuracy:.1f} %"
        )
        chosen = counts
        if len(curve) >= 2 and curve[-1]["accuracy"] - curve[-2]["accuracy"] < LEVEL_OFF:
            break
    trained = _train(design, chosen, models, seed, curve, progress)
    trained.key = design.key(chosen)
    store.save(f"choice-{design.key(chosen)}.pkl", pickle.dumps(trained))
    store.save(plan_name, json.dumps(chosen).encode())
    return trained


def _counts(models: list[str], pools: int) -> dict[str, int]:
    # "No effect" has no strength to cover: half the pools (its datasets differ by noise
    # and, with the tilt a nuisance, by the tilt).
    return {m: (max(4, pools // 2) if m == NO_EFFECT else pools) for m in models}


@dataclass
class _OutOfFold:
    """The table's datasets of one design and size with their out-of-fold predictions."""

    hand: np.ndarray  # hand-made summaries
    learned: np.ndarray  # learned summaries, out of fold
    y: np.ndarray
    groups: np.ndarray
    strength: np.ndarray
    tilt: np.ndarray
    sets: list
    votes: np.ndarray  # the forest's votes, out of fold
    calibrated: np.ndarray  # the votes calibrated by maps fitted on other folds

    @property
    def features(self) -> np.ndarray:
        return np.hstack([self.hand, self.learned])

    def no_effect_null(self, models: list[str]) -> np.ndarray:
        """The out-of-fold posterior probability of "no effect" of every effect-free
        dataset, sorted (the learned detection's null distribution)."""
        if NO_EFFECT not in models:
            return np.zeros(0)
        k = models.index(NO_EFFECT)
        return np.sort(self.calibrated[self.y == k, k])


def _out_of_fold(design: _Design, counts, models, seed, progress) -> _OutOfFold:
    X, y, groups, strength, tilt, sets = design.arrays(counts)
    classes = len(models)
    # The learned summary of every table dataset out of fold (per-drop classifiers trained
    # on the other folds' pools, the folds the forest is cross-validated on), so that the
    # forest learns from summaries as noisy as a new dataset's (stacking, Wolpert 1992).
    progress("model choice: learning a summary from single drops")
    slices = np.array([d.part >= 0 for d in sets])
    learned_oof = None
    for train, test in _group_folds(y, groups, seed):
        mine = train[slices[train]] if slices[train].any() else train
        fold = design.learned(models, seed).fit([sets[i].drops for i in mine], y[mine])
        part = fold.transform([sets[i].drops for i in test])
        if learned_oof is None:
            learned_oof = np.zeros((len(y), part.shape[1]))
        learned_oof[test] = part
    votes = _cross_validated(np.hstack([X, learned_oof]), y, groups, classes, seed)
    # The calibration map's own check: fitted on some folds' out-of-fold votes, applied to
    # the others (so the reported calibration error is out of sample twice over).
    calibrated = np.zeros_like(votes)
    for train, test in _group_folds(y, groups, seed + 1):
        calibrated[test] = _Calibrator.fit(votes[train], y[train]).apply(votes[test], classes)
    return _OutOfFold(X, learned_oof, y, groups, strength, tilt, sets, votes, calibrated)


def _train(design: _Design, counts, models, seed, curve, progress) -> ModelChoice:
    progress("model choice: training and cross-validating the classifier")
    oof = _out_of_fold(design, counts, models, seed, progress)
    hand, y, groups, strength, tilt = oof.hand, oof.y, oof.groups, oof.strength, oof.tilt
    sets, votes, calibrated = oof.sets, oof.votes, oof.calibrated
    X = oof.features
    slices = np.array([d.part >= 0 for d in sets])
    mine = np.flatnonzero(slices) if slices.any() else np.arange(len(y))
    learned = design.learned(models, seed).fit([sets[i].drops for i in mine], y[mine])
    calibrator = _Calibrator.fit(votes, y)
    forest = _forest(seed).fit(X, y)
    strengths = {}
    for k, m in enumerate(models):
        if m == NO_EFFECT:
            continue
        mine = y == k
        progress(f"model choice: strength intervals of {m}")
        strengths[m] = _fit_interval(
            hand[mine], strength[mine], groups[mine], tuple(EFFECTS.get(m).prior), seed
        )
    tilts = {}
    if design.table.release_tilt == "fitted":
        for k, m in enumerate(models):
            mine = y == k
            tilts[m] = _fit_interval(hand[mine], tilt[mine], groups[mine], NUISANCE_TILT_DEG, seed)
    ood = _OutOfDistribution.fit(hand, groups, seed)
    no_effect_null = oof.no_effect_null(models)
    checks = design_checks(models, y, groups, strength, votes, calibrated, curve, strengths)
    checks["datasets"] = len(y)
    checks["seed"] = seed
    checks["pools"] = {m: int(c) for m, c in counts.items()}
    checks["features"] = X.shape[1]
    names = design.feature_names + learned.names(models)
    return ModelChoice(
        models, names, forest, calibrator, strengths, tilts, ood, learned, no_effect_null, checks
    )

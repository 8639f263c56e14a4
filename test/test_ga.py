"""GA operators, single parent mating, reproducibility and structure recovery."""

import numpy as np
import pytest

from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.identify import identify
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.ga import (
    GAConfig,
    crossover,
    mutate,
    roulette_fitness,
    roulette_select,
    run_ga,
    spm_mating,
)

from .conftest import EQ1, EQ2


def test_spm_pairs_each_parent_with_its_own_inverse():
    rng = np.random.default_rng(0)
    pool = rng.random((100, 44)) < 0.5
    cfg = GAConfig(crossover_prob=1.0)
    children = spm_mating(pool, 99, 0.15, cfg, np.random.default_rng(1))
    n_spm = 15
    assert children.shape == (99, 44)
    c1, c2 = children[:n_spm], children[n_spm: 2 * n_spm]
    for i in range(n_spm):
        parent = pool[i]
        # child 2 is the bitwise complement of child 1: parent and inverse swapped
        assert np.array_equal(c2[i], ~c1[i])
        # child 1 starts with the parent and ends with its inverse, at one cut point
        cut = np.flatnonzero(c1[i] != parent)
        assert cut.size and np.array_equal(cut, np.arange(cut[0], 44))
    # without crossover the SPM children are the parent and its exact inverse
    plain = spm_mating(pool, 99, 0.15, GAConfig(crossover_prob=0.0), np.random.default_rng(1))
    assert np.array_equal(plain[:n_spm], pool[:n_spm])
    assert np.array_equal(plain[n_spm:2 * n_spm], ~pool[:n_spm])


def test_spm_zero_makes_no_inverses():
    rng = np.random.default_rng(0)
    pool = rng.random((100, 44)) < 0.5
    children = spm_mating(pool, 99, 0.0, GAConfig(crossover_prob=0.0), np.random.default_rng(1))
    # with no crossover, every child is a copy of a pool member, never an inverse
    pool_rows = {row.tobytes() for row in pool}
    assert all(child.tobytes() in pool_rows for child in children)
    inverses = {(~row).tobytes() for row in pool}
    assert not any(child.tobytes() in inverses for child in children)
    # ordinary pairs keep each bit from one of the two parents
    crossed = spm_mating(pool, 99, 0.0, GAConfig(crossover_prob=1.0), np.random.default_rng(1))
    a, b = pool[0:98:2], pool[1:99:2]
    assert np.array_equal(crossed[0:98:2] ^ crossed[1:99:2], a ^ b)


def test_operators():
    rng = np.random.default_rng(0)
    a = np.zeros((1000, 10), dtype=bool)
    b = np.ones((1000, 10), dtype=bool)
    c1, c2 = crossover(a, b, 0.6, rng)
    crossed = c1.any(axis=1)
    assert 0.55 < crossed.mean() < 0.65
    assert np.array_equal(c1, ~c2)
    flips = mutate(np.zeros((2000, 50), dtype=bool), 0.01, rng).mean()
    assert 0.008 < flips < 0.012
    fit = roulette_fitness(np.array([-10.0, -12.0, np.inf, -11.0]))
    assert fit[2] == 0 and fit[1] == fit.max() and np.all(fit[[0, 1, 3]] > 0)
    for kind in ("rank", "window"):
        f = roulette_fitness(np.array([-10.0, -12.0, np.inf]), kind)
        assert f[2] == 0 and f[1] > f[0] > 0
    picks = roulette_select(np.array([0.0, 1.0, 3.0]), 40000, rng)
    assert not np.any(picks == 0)
    assert np.mean(picks == 2) == pytest.approx(0.75, abs=0.02)


@pytest.mark.parametrize("kwargs", [
    {"population_size": 1}, {"generations": -1}, {"crossover_prob": 1.5},
    {"mutation_prob": -0.1}, {"spm_fraction": 0.6},
])
def test_invalid_ga_settings(kwargs):
    with pytest.raises(ValueError):
        GAConfig(**kwargs)


def test_seeded_runs_are_reproducible(robot_arm):
    u, y = robot_arm
    ts = TermSpace()
    P, t = ts.regression_matrix(u, y), ts.target(y)
    cfg = GAConfig(population_size=60, generations=40)
    runs = [run_ga(StructureEvaluator(P, t, "aic"), cfg, seed=s) for s in (7, 7, 8)]
    assert np.array_equal(runs[0].best_mask, runs[1].best_mask)
    assert np.array_equal(runs[0].history_array("mean"), runs[1].history_array("mean"))
    assert not np.array_equal(runs[0].history_array("mean"), runs[2].history_array("mean"))
    h = runs[0]
    assert len(h.history) == 41
    assert np.all(np.diff(h.history_array("best")) <= 0)  # elitism: never worse
    assert np.all(np.diff(h.history_array("evaluations")) >= 0)
    assert h.history[-1].evaluations == h.evaluations


def test_callback_sees_every_generation_and_can_stop(robot_arm):
    u, y = robot_arm
    ts = TermSpace()
    seen = []

    def cb(stats):
        seen.append(stats.generation)
        return stats.generation < 5

    res = run_ga(StructureEvaluator(ts.regression_matrix(u, y), ts.target(y)),
                 GAConfig(generations=50), seed=0, callback=cb)
    assert seen == [0, 1, 2, 3, 4, 5] and res.stopped_early


@pytest.mark.parametrize("criterion, expected, value", [
    ("aic", EQ1, -10744.78), ("bic", EQ2, -10707.48)])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_spm_ga_finds_the_papers_models(robot_arm, criterion, expected, value, seed):
    u, y = robot_arm
    res = identify(u=u, y=y, criterion=criterion, seed=seed)  # paper's settings, SPM 0.15
    assert res.model.terms == expected
    assert res.ga.best_score == pytest.approx(value, abs=0.01)
    assert res.ga.evaluations < res.ga.lookups  # the cache did its work


def test_ga_recovers_a_known_synthetic_structure():
    rng = np.random.default_rng(42)
    n = 800
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    e = 0.02 * rng.normal(size=n)
    for t in range(2, n):
        y[t] = (0.5 * y[t - 1] - 0.3 * y[t - 2] + 0.8 * u[t - 1]
                + 0.4 * u[t - 2] * y[t - 1] - 0.25 * u[t - 1] ** 2 + e[t])
    ts = TermSpace(ny=2, nu=2, degree=2)
    truth = ["y(t-1)", "y(t-2)", "u(t-1)", "u(t-1)^2", "y(t-1)*u(t-2)"]
    for seed in (0, 1):
        res = identify(u=u, y=y, term_space=ts, criterion="bic", seed=seed,
                       ga=GAConfig(population_size=100, generations=100))
        assert sorted(res.model.terms) == sorted(truth)
        coef = dict(zip(res.model.terms, res.model.coefficients))
        assert coef["y(t-1)*u(t-2)"] == pytest.approx(0.4, abs=0.03)
        assert coef["u(t-1)^2"] == pytest.approx(-0.25, abs=0.03)

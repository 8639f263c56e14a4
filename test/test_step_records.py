"""Step tests, the commonest robot experiment: held-out folds must each see the input change.

A first-order response to one step, noise-free: every path returns the exact model
``y(t) = 0.9y(t-1) + 0.1u(t-1)`` (before, the fold that held out the step could not
see the input's effect and the simulation focus lost the model).
"""

import numpy as np
import pytest

from spm_sysid.core.defaults import MIN_FOLD_EXCITATION
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.identify import identify
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.select.folds import blocked_folds, fold_excitation, informative_folds

EXACT = ["y(t-1)", "u(t-1)"]


def step_record(n: int = 1024, at: int = 500, noise: float = 0.0, seed: int = 0):
    u = np.zeros(n)
    u[at:] = 1.0
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = 0.9 * y[t - 1] + 0.1 * u[t - 1]
    return u, y + noise * np.random.default_rng(seed).standard_normal(n)


CASES = {
    "plain identify": dict(),
    "simulation focus, first order": dict(focus="simulation",
                                          term_space=TermSpace(ny=1, nu=1, degree=1)),
    "simulation focus, the paper's space": dict(focus="simulation"),
    "validated selection": dict(selection="validated"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_noise_free_step_response_gives_the_exact_model(case):
    u, y = step_record()
    model = identify(u=u, y=y, seed=1, **CASES[case]).model
    assert model.terms == EXACT, model.equation()
    assert np.allclose(model.coefficients, [0.9, 0.1], atol=1e-9)


def test_contiguous_folds_of_a_step_record_see_no_excitation_and_interleaved_ones_do():
    u, y = step_record()
    problem = Problem.from_signals(u, y, TermSpace(ny=1, nu=1, degree=1))
    assert fold_excitation(problem, blocked_folds(problem, 3, 3)) < 0.01
    folds, note = informative_folds(problem, 3, 3)
    assert folds and fold_excitation(problem, folds) >= MIN_FOLD_EXCITATION
    assert "dealt to 3 folds in turn" in note and "step test" in note
    # every sample is held out by one fold: the sub-blocks are the folds
    held = np.zeros(len(y), dtype=int)
    for f in folds:
        for a, b in f.held_out:
            held[a:b] += 1
    assert held.max() == 1


def test_real_records_keep_their_contiguous_folds(robot_arm):
    u, y = robot_arm
    problem = Problem.from_signals(u, y, TermSpace())
    folds, note = informative_folds(problem, 3, 3)
    assert note == "" and len(folds) == 9
    assert fold_excitation(problem, folds) > 0.8


def test_a_search_whose_first_draw_cannot_be_fitted_starts_with_smaller_structures():
    """The step record around its means: every structure of the first draw is rank-deficient."""
    from spm_sysid.core.fit.evaluator import structure_keys
    from spm_sysid.core.search.ga import GAConfig, run_ga

    u, y = step_record()
    problem = Problem.from_signals(u - u.mean(), y - y.mean(), TermSpace(constant=True))
    evaluator = problem.evaluator("aic")
    config = GAConfig()
    init_prob, _ = config.rates(evaluator.n_terms)
    first = np.random.default_rng(1).random((config.population_size, evaluator.n_terms))
    first = first < init_prob
    assert not np.isfinite(evaluator.score(first, structure_keys(first))).any()
    result = run_ga(problem.evaluator("aic"), config, seed=1)
    assert np.isfinite(result.best_score)  # before: inf, 'no structure could be fitted'
    assert result.history[0].best < np.inf


@pytest.mark.parametrize("levels", [(1.0, 2.0), (-0.3, 0.7)])
def test_a_two_level_inputs_square_repeats_it_when_the_constant_is_a_candidate(levels):
    """u^2 = (a + b) u - a b: with the constant, the square adds nothing and is left out."""
    u, _ = step_record()
    u = np.where(u > 0, levels[1], levels[0])
    rng = np.random.default_rng(0)
    y = np.convolve(u, [0.0, 0.5, 0.25])[:len(u)] + 0.01 * rng.standard_normal(len(u))
    with_constant = Problem.from_signals(u, y, TermSpace(ny=1, nu=1, constant=True))
    assert with_constant.excluded_terms()["duplicate"] == {"u(t-1)^2": "u(t-1)"}
    without = Problem.from_signals(u, y, TermSpace(ny=1, nu=1))
    assert without.excluded_terms()["duplicate"] == {}

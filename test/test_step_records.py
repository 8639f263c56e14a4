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


def _two_level_record(levels=(1.0, 2.0), n: int = 600):
    """A PRBS-like input of two levels; the output driven by the input's square."""
    rng = np.random.default_rng(3)
    u = np.where(np.repeat(rng.random(n // 6) < 0.5, 6), levels[1], levels[0])
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = 0.5 * y[t - 1] + 0.4 * u[t - 1] ** 2
    return u, y + 0.01 * rng.standard_normal(n)


def test_a_two_level_inputs_square_stays_a_term_of_its_own():
    """u^2 = 3u - 2 on levels 1 and 2: alone it is not u, so it stays a candidate.

    The plant is y(t) = 0.5y(t-1) + 0.4u(t-1)^2: two terms with the square, three
    (u, the constant) without it. The search and its certificate must find the
    optimum of every structure of the space, counted by brute force (before, the
    square was left out as "u plus a constant" and the optimum was lost).
    """
    u, y = _two_level_record()
    space = TermSpace(ny=1, nu=1, degree=2, constant=True)
    problem = Problem.from_signals(u, y, space)
    assert problem.excluded_terms()["duplicate"] == {}
    evaluator = problem.evaluator("aic")
    m = evaluator.n_terms
    every = (np.arange(1, 2 ** m)[:, None] >> np.arange(m)) & 1 == 1
    brute = float(np.min(evaluator.score(every)))
    model = identify(u=u, y=y, term_space=space, criterion="aic", seed=1,
                     operating_point="none").model
    assert [str(t) for t in model.terms] == ["y(t-1)", "u(t-1)^2"]
    assert model.criterion_value == pytest.approx(brute, abs=1e-6)
    assert model.metadata["certificate"]["status"] == "optimal"


def test_a_square_equal_to_a_number_repeats_the_constant():
    """Levels -1 and 1: u^2 is 1 on every row, the constant's column; it is left out."""
    u, y = _two_level_record((-1.0, 1.0))
    with_constant = Problem.from_signals(u, y, TermSpace(ny=1, nu=1, constant=True))
    assert with_constant.excluded_terms()["duplicate"] == {"u(t-1)^2": "1"}
    without = Problem.from_signals(u, y, TermSpace(ny=1, nu=1))
    assert without.excluded_terms()["duplicate"] == {}


def test_of_structures_that_fit_exactly_the_lowest_degree_is_taken():
    """Around its means the step fits with y(t-1)*u(t-1) as exactly as with y(t-1).

    Both score the SSE floor with three terms: a tie, which the search met in
    either order; the tie goes to the linear structure, the plant's.
    """
    from spm_sysid.core.search.ties import lowest_degree_of_ties

    u, y = step_record()
    problem = Problem.from_signals(u - u.mean(), y - y.mean(),
                                   TermSpace(ny=1, nu=1, degree=2, constant=True))
    names = [n for n, ok in zip(problem.term_space.term_names(), problem.usable) if ok]
    evaluator = problem.evaluator("aic")

    def mask(*terms):
        return np.isin(names, terms)

    product, plant = mask("1", "u(t-1)", "y(t-1)*u(t-1)"), mask("1", "y(t-1)", "u(t-1)")
    values = evaluator.score(np.array([product, plant]))
    assert values[0] == values[1]  # a tie at the floor
    degrees = problem.term_space.term_degrees[problem.usable]
    out = lowest_degree_of_ties(evaluator, product, degrees)
    assert sorted(np.array(names)[out]) == sorted(["1", "y(t-1)", "u(t-1)"])


def test_noisy_data_have_no_ties_to_resolve(robot_arm):
    """Nothing moves where no fit is exact: the robot arm's optimum, a noisy nonlinear one."""
    from spm_sysid.core.search.ties import lowest_degree_of_ties

    for (u, y), space in ((robot_arm, TermSpace()),
                          (_two_level_record(), TermSpace(ny=1, nu=1, degree=2, constant=True))):
        problem = Problem.from_signals(u, y, space)
        model = identify(u=u, y=y, term_space=space, seed=1, operating_point="none").model
        best = np.isin(space.term_names(), [str(t) for t in model.terms])[problem.usable]
        out = lowest_degree_of_ties(problem.evaluator("aic"), best,
                                    space.term_degrees[problem.usable])
        assert np.array_equal(out, best)

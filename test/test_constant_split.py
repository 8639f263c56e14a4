"""A two-level input with the constant a candidate: the space certified as two searches.

``u^2 = 3u - 2`` on levels 1 and 2: with the constant, the square stands for
``u``; without it, it is a term of its own. The split certification
(:mod:`spm_sysid.core.search.split`) must give the optimum of every structure of
the space, counted by brute force, wherever it lies.
"""

import numpy as np
import pytest

from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.search.split import certify_split

SPACE = TermSpace(ny=2, nu=2, degree=2, constant=True)


def _record(plant, levels=(1.0, 2.0), n: int = 800, seed: int = 3):
    rng = np.random.default_rng(seed)
    u = np.where(np.repeat(rng.random(n // 5) < 0.5, 5), levels[1], levels[0])
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = plant(y[t - 1], y[t - 2], u[t - 1], u[t - 2])
    return u, y + 0.01 * rng.standard_normal(n)


PLANTS = {
    "the square, no constant": lambda y1, y2, u1, u2: 0.5 * y1 + 0.4 * u1 ** 2,
    "linear with an offset": lambda y1, y2, u1, u2: 0.6 * y1 - 0.1 * y2 + 0.3 * u2 + 0.2,
    "a product and a square": lambda y1, y2, u1, u2: 0.5 * y1 + 0.1 * y1 * u1 - 0.2 * u2 ** 2,
}


def _brute_force(evaluator) -> float:
    m = evaluator.n_terms
    best = np.inf
    for start in range(1, 2 ** m, 1 << 14):  # in batches of bounded memory
        codes = np.arange(start, min(start + (1 << 14), 2 ** m))
        best = min(best, float(np.min(evaluator.score((codes[:, None] >> np.arange(m)) & 1
                                                      == 1))))
    return best


def test_the_split_names_each_square_and_the_column_it_repeats():
    u, y = _record(PLANTS["the square, no constant"])
    problem = Problem.from_signals(u, y, SPACE)
    constant, source = problem.constant_split()
    names = [n for n, ok in zip(SPACE.term_names(), problem.usable) if ok]
    assert constant == 0 and names[0] == "1"
    assert {names[j]: names[i] for j, i in enumerate(source) if i >= 0} == {
        "u(t-1)^2": "u(t-1)", "u(t-2)^2": "u(t-2)"}
    # levels -1 and 1: the square is the constant's column itself, left out as a repeat
    u2, y2 = _record(PLANTS["linear with an offset"], levels=(-1.0, 1.0))
    symmetric = Problem.from_signals(u2, y2, SPACE)
    assert symmetric.excluded_terms()["duplicate"] == {"u(t-1)^2": "1", "u(t-2)^2": "1"}
    assert (symmetric.constant_split()[1] < 0).all()


@pytest.mark.parametrize("plant", list(PLANTS))
@pytest.mark.parametrize("criterion", ["aic", "bic"])
def test_the_split_certificate_is_the_brute_force_optimum(plant, criterion):
    u, y = _record(PLANTS[plant])
    problem = Problem.from_signals(u, y, SPACE)
    evaluator = problem.evaluator(criterion)
    assert evaluator.n_terms == 15  # 2^15 structures: brute force in a second
    cert = certify_split(evaluator, problem.constant_split(), time_limit=60)
    brute = _brute_force(evaluator)
    assert cert.status == "optimal"
    assert cert.value == pytest.approx(brute, abs=1e-6)
    assert cert.lower_bound == pytest.approx(cert.value)
    assert evaluator.score(cert.mask[None, :])[0] == pytest.approx(cert.value)


def test_a_split_search_stopped_early_bounds_the_optimum_from_below():
    u, y = _record(PLANTS["a product and a square"])
    problem = Problem.from_signals(u, y, SPACE)
    evaluator = problem.evaluator("aic")
    cert = certify_split(evaluator, problem.constant_split(), time_limit=60, node_limit=1)
    brute = _brute_force(evaluator)
    assert cert.status == "limit" and cert.reason
    assert cert.lower_bound <= brute + 1e-6 <= cert.value + 2e-6
    assert "two spaces" in cert.bound


def test_a_cutoff_asks_only_for_structures_below_it():
    """The second half's cutoff: above the optimum it is found; below, none is, proved."""
    from spm_sysid.core.search.certify import certify

    u, y = _record(PLANTS["linear with an offset"])
    evaluator = Problem.from_signals(u, y, SPACE).evaluator("bic")
    brute = _brute_force(evaluator)
    above = certify(None, None, "bic", evaluator=evaluator, cutoff=brute + 5.0)
    assert above.status == "optimal" and above.value == pytest.approx(brute, abs=1e-6)
    below = certify(None, None, "bic", evaluator=evaluator, cutoff=brute - 5.0)
    assert below.status == "optimal"
    assert below.lower_bound == pytest.approx(brute - 5.0) and below.value >= brute - 1e-6

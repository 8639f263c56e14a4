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

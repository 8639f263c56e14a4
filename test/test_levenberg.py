"""The refinements' Levenberg-Marquardt, against scipy's MINPACK on the same problems."""

import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares

from spm_sysid.core.fit.levenberg import levenberg_marquardt


def _rosenbrock(x):
    r = np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])
    jac = np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])
    return r, jac


def _decay_problem(seed=0):
    """A decay and a large offset fitted to noisy samples: badly scaled columns."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 10.0, 400)
    model = lambda p: p[0] * np.exp(-p[1] * t) + p[2]  # noqa: E731
    y = model(np.array([3.0, 0.7, 200.0])) + rng.normal(0.0, 0.01, t.size)

    def evaluate(p):
        e = np.exp(-p[1] * t)
        return model(p) - y, np.column_stack([e, -p[0] * t * e, np.ones_like(t)])
    return evaluate, np.array([1.0, 0.3, 190.0])


def test_it_reaches_the_minimum_of_rosenbrock():
    sol = levenberg_marquardt(_rosenbrock, np.array([-1.2, 1.0]), 200)
    assert sol.x == pytest.approx([1.0, 1.0], abs=1e-6)
    assert sol.nfev <= 200 and "termination condition" in sol.message


def test_it_finds_minpacks_solution_of_a_badly_scaled_curve_fit():
    evaluate, start = _decay_problem()
    ours = levenberg_marquardt(evaluate, start, 500)
    ref = least_squares(lambda p: evaluate(p)[0], start, jac=lambda p: evaluate(p)[1],
                        method="lm", x_scale="jac", max_nfev=500)
    assert ref.success
    assert ours.x == pytest.approx(ref.x, rel=1e-5)
    r_ours, r_ref = evaluate(ours.x)[0], evaluate(ref.x)[0]
    assert r_ours @ r_ours == pytest.approx(r_ref @ r_ref, rel=1e-9)


def test_it_stops_at_the_evaluations_allowed_and_says_so():
    evaluate, start = _decay_problem(1)
    calls = []
    sol = levenberg_marquardt(lambda p: calls.append(1) or evaluate(p), start, 4)
    assert sol.nfev == len(calls) == 4
    assert "maximum number of function evaluations" in sol.message
    r0, r = evaluate(start)[0], evaluate(sol.x)[0]
    assert r @ r < r0 @ r0  # each accepted step lowers the sum of squares


def test_a_step_to_non_finite_residuals_is_rejected_and_a_non_finite_start_kept():
    evaluate, start = _decay_problem(2)

    def fenced(p):  # no finite residuals beyond a decay rate of 0.6 (a "divergence")
        r, jac = evaluate(p)
        return (np.full_like(r, np.inf), jac) if p[1] > 0.6 else (r, jac)

    sol = levenberg_marquardt(fenced, start, 300)  # the optimum (0.7) lies beyond the fence
    r0, r = evaluate(start)[0], fenced(sol.x)[0]
    assert sol.x[1] <= 0.6 and np.isfinite(r).all() and r @ r < r0 @ r0
    inf_start = levenberg_marquardt(lambda p: (np.full(3, np.nan), np.ones((3, 2))),
                                    np.array([1.0, 2.0]), 10)
    assert inf_start.nfev == 1 and inf_start.x == pytest.approx([1.0, 2.0])
    assert "not finite" in inf_start.message


def test_a_step_to_sensitivities_out_of_range_is_rejected_without_an_overflow():
    """A free run whose linearisation grows without bound gives Jacobians of 1e200: their
    J'J overflows, so such a point is no step (and no warning reaches the user)."""
    evaluate, start = _decay_problem(2)

    def exploding(p):  # finite residuals everywhere, sensitivities out of range beyond 0.6
        r, jac = evaluate(p)
        return (r, jac * 1e200) if p[1] > 0.6 else (r, jac)

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = levenberg_marquardt(exploding, start, 300)
        kept = levenberg_marquardt(lambda p: (np.ones(3), np.full((3, 2), 1e200)),
                                   np.array([1.0, 2.0]), 10)
    r0, r = evaluate(start)[0], evaluate(sol.x)[0]
    assert sol.x[1] <= 0.6 and r @ r < r0 @ r0
    assert kept.nfev == 1 and kept.x == pytest.approx([1.0, 2.0])
    assert "out of floating-point range" in kept.message


def test_the_steps_do_not_depend_on_the_coefficients_units():
    """Column scaling (MINPACK's, scipy's x_scale="jac"): coefficients in other units take
    the same steps, so terms of very different sizes are refined alike."""
    evaluate, start = _decay_problem(3)
    units = np.array([1e4, 1.0, 1e-4])
    scaled_calls, plain_calls = [], []

    def scaled(q):  # the same problem in q = p * units
        scaled_calls.append(q / units)
        r, jac = evaluate(q / units)
        return r, jac / units

    a = levenberg_marquardt(scaled, start * units, 8)
    b = levenberg_marquardt(lambda p: plain_calls.append(p) or evaluate(p), start, 8)
    assert a.nfev == b.nfev
    assert np.allclose(np.array(scaled_calls), np.array(plain_calls), rtol=1e-6)


def test_the_point_returned_is_the_best_evaluated():
    def tracked(x, seen):
        r, jac = _rosenbrock(x)
        seen.append(float(r @ r))
        return r, jac

    for allowed in range(2, 12):
        seen = []
        sol = levenberg_marquardt(lambda x, s=seen: tracked(x, s), np.array([-1.2, 1.0]),
                                  allowed)
        r = _rosenbrock(sol.x)[0]
        assert r @ r == pytest.approx(min(seen), rel=1e-12)


@pytest.mark.parametrize("segments", [None, [(0, 400), (450, 1024)]])
def test_the_compiled_refinement_takes_the_python_solvers_steps(robot_arm, segments):
    """A refinement runs as one compiled call (solver and simulations); the same code run in
    Python on the same residuals (evaluate_free_run) takes the same steps to the same point,
    and both lower the free-run error of the least-squares start."""
    from spm_sysid.core.fit.free_run import FreeRun
    from spm_sysid.core.fit.levenberg import evaluate_free_run, refine_free_run
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.model.terms import TermSpace

    u, y = robot_arm
    ts = TermSpace(ny=3, nu=3, degree=2)
    names = ts.term_names()
    keep = ["y(t-1)", "y(t-2)", "y(t-3)", "u(t-1)", "u(t-2)", "u(t-3)", "y(t-1)*u(t-1)"]
    mask = np.isin(names, keep)
    model = fit_structure(u, y, mask, ts)
    run = FreeRun(model, u, y, segments, guard=True)
    compiled = refine_free_run(run, model.coefficients, 30)
    plain = levenberg_marquardt(lambda t: evaluate_free_run(run, t)[:2], model.coefficients, 30)
    assert compiled.nfev == plain.nfev and compiled.message == plain.message
    assert compiled.x == pytest.approx(plain.x, rel=1e-9, abs=1e-12)
    r0 = evaluate_free_run(run, model.coefficients)[0]
    r = evaluate_free_run(run, compiled.x)[0]
    assert compiled.sse_start == pytest.approx(r0 @ r0, rel=1e-12)
    assert compiled.sse == pytest.approx(r @ r, rel=1e-12) and compiled.sse < 0.9 * (r0 @ r0)

"""A long record's candidate matrix is the only large array its problem makes (issue 41).

The matrix is built a block of rows at a time into one array, and the numbers
the search needs from it (column norms, the Gram matrix and triangular factor of
the evaluator, a fold's fit) are reduced from slices of its rows: no stacked,
squared, scaled or selected copy of it. Slices give the numbers of one pass
(checked here against the one-pass route on the robot-arm data), and the
allocations are counted by ``tracemalloc`` (numpy reports its arrays to it),
so the bound does not depend on this machine's free memory.
"""

import tracemalloc

import numpy as np
import pytest

import spm_sysid.core.fit.evaluator as evaluator_module
import spm_sysid.core.fit.lstsq as lstsq_module
import spm_sysid.core.memory as memory_module
import spm_sysid.core.model.narx as narx_module
import spm_sysid.core.model.terms as terms_module
from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.fit.lstsq import column_norms, reference_fit
from spm_sysid.core.fit.problem import Problem, excluded_columns
from spm_sysid.core.model.terms import TermSpace


def _small_slices(monkeypatch, size: int) -> None:
    monkeypatch.setattr(evaluator_module, "FACTOR_SLICE_BYTES", size)
    monkeypatch.setattr(lstsq_module, "NORM_SLICE_BYTES", size)
    monkeypatch.setattr(terms_module, "ROW_BLOCK_BYTES", size)


def test_slices_give_the_numbers_of_one_pass(robot_arm, monkeypatch):
    u, y = robot_arm
    space = TermSpace(ny=2, nu=2, degree=3)
    P, target = space.regression(u, y, [(0, 500), (500, len(y))])
    ev = StructureEvaluator(P, target, "aic")
    zero, duplicate = excluded_columns(P)
    _small_slices(monkeypatch, 8 * 45 * 37)  # 37 rows of 45 columns: 28 slices
    P2, target2 = space.regression(u, y, [(0, 500), (500, len(y))])
    assert np.array_equal(P2, P) and np.array_equal(target2, target)  # bit for bit
    np.testing.assert_allclose(column_norms(P), np.linalg.norm(P, axis=0), rtol=1e-13)
    z2, d2 = excluded_columns(P)
    assert np.array_equal(z2, zero) and np.array_equal(d2, duplicate)
    columns = np.arange(1, P.shape[1], 2)
    sliced = StructureEvaluator(P, target, "aic", columns=columns)
    whole = StructureEvaluator(P[:, columns], target, "aic")
    assert sliced.n_terms == len(columns) and sliced.n == len(target)
    np.testing.assert_allclose(sliced.gram, whole.gram, rtol=1e-12, atol=1e-12)
    # the factor is the same up to the sign of each row: R'R is the Gram matrix
    np.testing.assert_allclose(np.abs(sliced.factor), np.abs(whole.factor), atol=1e-10)
    masks = np.random.default_rng(0).random((200, len(columns))) < 0.2
    np.testing.assert_allclose(sliced.score(masks), whole.score(masks), rtol=1e-9)
    full = StructureEvaluator(P, target, "aic")
    np.testing.assert_allclose(full.gram, ev.gram, rtol=1e-12, atol=1e-12)


def _record(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] - 0.2 * y[t - 2] + u[t - 1] + 0.1 * u[t - 2] ** 2
    return u, y + 0.01 * rng.standard_normal(n)


def test_a_long_problem_allocates_its_matrix_once(monkeypatch):
    u, y = _record(30_000)
    space = TermSpace(ny=6, nu=6, degree=2)  # 91 candidate terms
    segments = [(0, 10_000), (10_000, 20_000), (20_000, 30_000)]
    matrix = 8 * (30_000 - 3 * 6) * space.n_terms
    _small_slices(monkeypatch, 1 << 20)
    tracemalloc.start()
    try:
        problem = Problem.from_signals(u, y, space, segments)
        problem.evaluator("aic")
        mask = np.zeros(space.n_terms, dtype=bool)
        mask[1:5] = True
        rows = np.arange(problem.rows) < 2 * problem.rows // 3
        fold = problem.fit(mask, rows=rows)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert problem.columns.nbytes == matrix
    # the matrix, a few slices of a megabyte and the structure's own columns
    assert peak < 1.3 * matrix, f"peak {peak / 2**20:.1f} MiB for a {matrix / 2**20:.1f} MiB matrix"
    # the fold's fit is the fit of those rows alone
    X = problem.columns[rows][:, mask]
    reference = reference_fit(X, problem.target[rows], np.ones(4, dtype=bool))
    np.testing.assert_allclose(fold.coefficients, reference.coefficients
                               * problem._factors[mask], rtol=1e-10)


@pytest.mark.parametrize("columns", [None, [0, 2, 5]])
def test_an_evaluator_of_fewer_rows_than_terms_still_factors(columns, monkeypatch):
    P = np.random.default_rng(1).standard_normal((5, 8))
    t = P[:, 0] - P[:, 2]
    _small_slices(monkeypatch, 8 * 9 * 2)
    ev = StructureEvaluator(P, t, "aic", columns=None if columns is None else np.array(columns))
    m = 8 if columns is None else 3
    assert ev.factor.shape == (min(5, m + 1), m + 2)
    X = P if columns is None else P[:, columns]
    aug = np.column_stack([X / np.linalg.norm(X, axis=0), t])
    np.testing.assert_allclose(ev.factor[:, :m + 1].T @ ev.factor[:, :m + 1], aug.T @ aug,
                               atol=1e-10)


def test_outputs_of_a_long_record_in_a_large_space_take_turns():
    from spm_sysid.core.defaults import PARALLEL_OUTPUT_BYTES
    from spm_sysid.core.jobs import JobSettings
    from spm_sysid.core.jobs.several import _outputs_at_once
    from spm_sysid.core.record import Record

    def at_once(n: int, order: int) -> tuple[int, int]:
        rng = np.random.default_rng(0)
        record = Record.from_samples(rng.standard_normal((n, 2)), rng.standard_normal((n, 2)),
                                     source="t", input_names=("tau1", "tau2"),
                                     output_names=("q1", "q2"))
        settings = JobSettings.from_values({"ny": order, "nu": order, "degree": 2})
        base = settings.for_signals(record.input_names, "q1")
        # each output's space: its own lags, both inputs' and the other output's
        terms = TermSpace(ny=order, nu=(order,) * 3, degree=2,
                          inputs=("tau1", "tau2", "q2")).n_terms
        return _outputs_at_once(record, base, [base.term_space] * 2), terms

    # the two-link arm's 4 000 samples in a (9, 9, 2) space: side by side
    small, terms = at_once(4000, 9)
    assert terms == 702 and small == 2
    # 10^5 samples: 2 x 8 bytes x ~67 000 estimation rows x 703 terms is past the budget
    large, _ = at_once(100_000, 9)
    assert large == 1 and 2 * 8 * 60_000 * terms > PARALLEL_OUTPUT_BYTES


def test_a_structure_fit_in_slices_is_the_fit_of_one_pass(robot_arm, monkeypatch):
    from spm_sysid.core.fit.lstsq import columns_product, structure_fit

    u, y = robot_arm
    P, target = TermSpace(ny=2, nu=2, degree=2).regression(u, y)
    cols = np.array([0, 1, 3, 6, 9])
    rows = np.random.default_rng(3).random(len(target)) < 0.7
    whole, whole_residuals = structure_fit(P, target, cols, rows)
    X = P[rows][:, cols]
    reference = reference_fit(X, target[rows], np.ones(len(cols), dtype=bool))
    assert np.array_equal(whole.coefficients, reference.coefficients)  # one pass: unchanged
    monkeypatch.setattr(memory_module, "STRUCTURE_SLICE_BYTES", 8 * 6 * 50)  # slices of 50 rows
    sliced, residuals = structure_fit(P, target, cols, rows)
    np.testing.assert_allclose(sliced.coefficients, reference.coefficients, rtol=1e-9)
    np.testing.assert_allclose(residuals, whole_residuals, rtol=1e-9, atol=1e-12)
    assert sliced.sse == pytest.approx(reference.sse, rel=1e-10)
    np.testing.assert_allclose(np.abs(sliced.r_factor), np.abs(reference.r_factor), atol=1e-10)
    np.testing.assert_allclose(columns_product(P, cols, sliced.coefficients, rows),
                               X @ sliced.coefficients, rtol=1e-12)
    # dependent or zero columns are rank-deficient in slices as in one pass
    twice = np.column_stack([P, 2.0 * P[:, 1], np.zeros(len(P))])
    for bad in ([0, 1, twice.shape[1] - 2], [0, twice.shape[1] - 1]):
        fit, none = structure_fit(twice, target, np.array(bad))
        assert fit.rank_deficient and none is None


def test_the_open_loop_check_in_slices_and_its_memory(monkeypatch):
    import spm_sysid.core.validate.open_loop as open_loop

    u, y = _record(300_000)
    y = np.cumsum(y) * 1e-3  # an integrating output: its pole at 1
    one_pass = open_loop.open_loop_check(u[:3000], y[:3000], [(0, 3000)], 4)
    monkeypatch.setattr(open_loop, "STRUCTURE_SLICE_BYTES", 8 * 10 * 400)
    sliced = open_loop.open_loop_check(u[:3000], y[:3000], [(0, 3000)], 4)
    assert sliced.kind == one_pass.kind == "integrating" and sliced.rows == one_pass.rows
    assert abs(sliced.pole - one_pass.pole) < 1e-9
    monkeypatch.setattr(open_loop, "STRUCTURE_SLICE_BYTES", 1 << 20)
    tracemalloc.start()
    try:
        long = open_loop.open_loop_check(u, y, [(0, 150_000), (150_000, 300_000)], 4)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert long.kind == "integrating" and long.rows == 300_000 - 8
    regressors = 8 * long.rows * 10  # one copy of the ARX regression matrix: 22.9 MiB
    assert peak < 0.3 * regressors, f"peak {peak / 2**20:.1f} MiB"  # one pass held five


def test_the_free_run_band_in_stretches_is_the_band_of_one_pass(robot_arm, monkeypatch):
    import spm_sysid.core.defaults as defaults
    import spm_sysid.core.model.uncertainty as uncertainty
    from spm_sysid.core.model.uncertainty import output_band

    u, y = robot_arm
    problem = Problem.from_signals(u, y, TermSpace(ny=4, nu=4, degree=1))
    model = problem.model(np.arange(problem.term_space.n_terms) < 8)
    segments = [(0, 400), (400, 1024)]
    one_pass = output_band(model, u, y, horizon=None, segments=segments, draws=40)
    monkeypatch.setattr(defaults, "BAND_VALUES", 40 * 150)  # the band in stretches,
    monkeypatch.setattr(uncertainty, "_STRETCH_VALUES", 40 * 150)  # each of 150 rows
    stretches = output_band(model, u, y, horizon=None, segments=segments, draws=40)
    assert stretches.draws == one_pass.draws == 40
    assert np.array_equal(stretches.lower, one_pass.lower)  # the same runs, bit for bit
    assert np.array_equal(stretches.upper, one_pass.upper)
    assert stretches.diverged == one_pass.diverged
    # a long record: the draws' runs are never all held at once
    n = 200_000
    uu, yy = np.tile(u, n // len(u) + 1)[:n], np.tile(y, n // len(y) + 1)[:n]
    monkeypatch.setattr(defaults, "BAND_VALUES", 40 * 10_000)
    monkeypatch.setattr(uncertainty, "_STRETCH_VALUES", 40 * 10_000)
    tracemalloc.start()
    try:
        band = output_band(model, uu, yy, horizon=None, segments=[(0, n)], draws=40)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert band.draws == 40 and len(band.lower) == n - 4
    assert peak < 0.35 * 40 * n * 8, f"peak {peak / 2**20:.1f} MiB"  # one pass: all 61 MiB


def test_fold_excitation_from_slices_is_the_whitened_measure(robot_arm, monkeypatch):
    import spm_sysid.core.select.folds as folds_module

    u, y = robot_arm
    problem = Problem.from_signals(u, y, TermSpace(ny=3, nu=3, degree=2))
    folds = folds_module.blocked_folds(problem, 4)
    linear = (problem.term_space.term_degrees <= 1) & problem.usable
    X = problem.columns[:, linear]
    X = X / np.sqrt(np.mean(X * X, axis=0))
    w, V = np.linalg.eigh(X.T @ X / len(X))
    keep = w >= folds_module.EXCITED_DIRECTIONS * w[-1]
    Z = X @ V[:, keep] / np.sqrt(w[keep])
    direct = min(np.linalg.eigvalsh(Z[f.train].T @ Z[f.train] / f.train.sum())[0]
                 for f in folds) ** 0.5
    assert folds_module.fold_excitation(problem, folds) == pytest.approx(direct, rel=1e-10)
    monkeypatch.setattr(folds_module, "FACTOR_SLICE_BYTES", 8 * 7 * 60)
    assert folds_module.fold_excitation(problem, folds) == pytest.approx(direct, rel=1e-10)


def _two_link_linear(order: int):
    from spm_sysid.core.model.mimo import MimoModel, output_space
    from spm_sysid.core.model.narx import NarxModel

    space = TermSpace(ny=order, nu=order, degree=2, inputs=("tau1", "tau2"), output="q")
    models = []
    for i in range(2):
        sp = output_space(space, ("q1", "q2"), i)
        chosen = [j for j, d in enumerate(sp.term_degrees) if d == 1][: 3 * order + i]
        chosen += [j for j, d in enumerate(sp.term_degrees) if d == 2][:2]  # and products
        models.append(NarxModel(sp, chosen, np.zeros(len(chosen))))
    return MimoModel(("q1", "q2"), ("tau1", "tau2"), models)


def test_coupled_fits_from_shared_factors_are_the_direct_fits(monkeypatch):
    """The coupled judgement's fold fits: pieces factored once give each set's direct fit."""
    from benchmarks.two_link import record
    from spm_sysid.core.select import coupled_fits
    from spm_sysid.core.select.coupled import coupled_folds

    tau, q = record(3000, seed=0)
    model = _two_link_linear(3)
    segments = [(0, 1700), (1750, 3000)]  # a gap: rows never cross it
    folds = coupled_folds(segments, len(q), model.max_lag)
    sets = [train for _, train in folds] + [segments, [(0, 12)], []]
    direct = coupled_fits.least_squares_fits(model, tau, q, sets)
    assert coupled_fits._direct(model, len(q))  # 3000 rows fit one slice: the old route
    calls = []
    monkeypatch.setattr(coupled_fits, "slice_rows", lambda k: 97)  # slices of 97 rows
    monkeypatch.setattr(narx_module, "slice_rows", lambda k: 97)
    real = coupled_fits._factor
    monkeypatch.setattr(coupled_fits, "_factor", lambda *a: calls.append(a[-1]) or real(*a))
    shared = coupled_fits.least_squares_fits(model, tau, q, sets)
    assert len(folds) == 6 and len(calls) <= 2 * (2 * len(folds) + 6)  # pieces, not sets
    for d, s in zip(direct[:-2], shared[:-2]):
        for a, b in zip(d.models, s.models):
            np.testing.assert_allclose(b.coefficients, a.coefficients, rtol=1e-9, atol=1e-12)
    assert shared[-2] is None and direct[-2] is None  # 9 rows, 11 terms or more
    assert shared[-1] is None and direct[-1] is None  # no rows
    # dependent columns: the same term twice is rank-deficient on either route
    twice = model.models[0]
    bad = type(model)(model.outputs, model.inputs,
                      [type(twice)(twice.term_space, [*twice.term_indices, twice.term_indices[0]],
                                   np.zeros(len(twice.term_indices) + 1)), model.models[1]])
    assert coupled_fits.least_squares_fits(bad, tau, q, [segments]) == [None]
    monkeypatch.setattr(coupled_fits, "slice_rows", lambda k: 10**9)
    assert coupled_fits.least_squares_fits(bad, tau, q, [segments]) == [None]


def test_a_coupled_finalists_account_from_its_factor_is_the_direct_one(monkeypatch):
    """The chosen finalist's SSE, column norms and standard errors, from slices of rows."""
    from benchmarks.two_link import record
    from spm_sysid.core.model.mimo import augmented_inputs
    from spm_sysid.core.model.uncertainty import from_jacobian
    from spm_sysid.core.select import coupled, coupled_fits

    tau, q = record(3000, seed=0)
    segments = [(0, 1700), (1750, 3000)]
    model = coupled_fits.fit_least_squares(_two_link_linear(3), tau, q, segments)
    model = type(model)(model.outputs, model.inputs,  # other coefficients: a nonzero error
                        [type(m)(m.term_space, m.term_indices, 0.9 * m.coefficients)
                         for m in model.models])
    for i, m in enumerate(model.models):
        u_aug = augmented_inputs(tau, q, i)
        P, t_norm, sse, rows = coupled._one_step_sums(m, u_aug, q[:, i], segments)
        assert P.shape[0] == rows == 3000 - 50 - 2 * m.term_space.max_lag  # P built whole
        with monkeypatch.context() as patch:
            patch.setattr(coupled_fits, "slice_rows", lambda k: 97)
            patch.setattr(narx_module, "slice_rows", lambda k: 97)
            R, t_norm2, sse2, rows2 = coupled._one_step_sums(m, u_aug, q[:, i], segments)
        assert R.shape == (P.shape[1], P.shape[1]) and rows2 == rows
        np.testing.assert_allclose(np.linalg.norm(R, axis=0), np.linalg.norm(P, axis=0),
                                   rtol=1e-12)
        assert t_norm2 == pytest.approx(t_norm, rel=1e-12)
        assert sse2 == pytest.approx(sse, rel=1e-9)
        np.testing.assert_allclose(from_jacobian(R, sse2, rows2).covariance,
                                   from_jacobian(P, sse).covariance, rtol=1e-8)


def test_long_one_step_predictions_and_covariances_in_slices(robot_arm, monkeypatch):
    """One-step predictions and the Gauss-Newton covariance, a slice of rows at a time."""
    import spm_sysid.core.model.uncertainty as uncertainty_module
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.model.uncertainty import from_jacobian

    u, y = robot_arm
    space = TermSpace(ny=2, nu=2, degree=2)
    model = fit_structure(u, y, np.ones(space.n_terms, dtype=bool), space)
    segments = [(0, 500), (530, len(y))]
    whole = model.predict(u, y, segments)
    P, _ = space.regression(u, y, segments)
    whole_cov = from_jacobian(P, 1.0).covariance
    monkeypatch.setattr(narx_module, "slice_rows", lambda k: 61)  # 17 slices
    monkeypatch.setattr(uncertainty_module, "slice_rows", lambda k: 61)
    np.testing.assert_allclose(model.predict(u, y, segments), whole, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(from_jacobian(P, 1.0).covariance, whole_cov, rtol=1e-9)


def test_a_long_final_refinement_fits_on_windows_within_its_jacobian_budget(monkeypatch):
    """A single output's final refinement: every sample while its Jacobian fits, else windows."""
    import spm_sysid.core.select.folds as folds

    segments = [(0, 60_000), (60_000, 100_000)]
    assert folds.final_samples(segments, 4, 8 * 60, single=True) == segments  # 48 MB
    assert folds.final_samples(segments, 4, 8 * 120) == segments  # 96 MB: two outputs'
    windows = folds.final_samples(segments, 4, 8 * 120, single=True)  # past 64 MB
    rows = sum(b - a for a, b in windows)
    assert 60_000 <= rows <= (64 << 20) // (8 * 120) and windows[-1][1] > 90_000
    monkeypatch.setattr(folds, "FINAL_JACOBIAN_BYTES", 20_000 * 8 * 60)
    windows = folds.final_samples(segments, 4, 8 * 60, single=True)
    rows = sum(b - a for a, b in windows)
    assert 15_000 <= rows <= 20_000 and windows[0][0] < 10_000 and windows[-1][1] > 90_000


def test_the_one_step_band_in_slices_is_the_band_of_one_pass(robot_arm, monkeypatch):
    from spm_sysid.core.model.uncertainty import output_band

    u, y = robot_arm
    model = _eq1_with_uncertainty(robot_arm)
    segments = [(0, 500), (530, len(y))]
    whole = output_band(model, u, y, horizon=1, segments=segments)
    monkeypatch.setattr(narx_module, "slice_rows", lambda k: 61)
    sliced = output_band(model, u, y, horizon=1, segments=segments)
    np.testing.assert_allclose(sliced.lower, whole.lower, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sliced.upper, whole.upper, rtol=1e-12, atol=1e-15)
    assert len(whole.lower) == 1024 - 30 - 2 * 4


def _eq1_with_uncertainty(robot_arm):
    from spm_sysid.core.fit.problem import fit_structure

    u, y = robot_arm
    mask = np.zeros(44, dtype=bool)
    mask[:8] = True
    model = fit_structure(u, y, mask, TermSpace())
    assert model.uncertainty is not None
    return model

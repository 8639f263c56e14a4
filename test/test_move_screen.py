"""The polish's move screen: every single-term move's SSE from the least-squares factor.

Checked against plain least squares (numpy's lstsq on the regression matrix) on the
real robot-arm data at 84 candidates, and the descent it drives against the
evaluator's own exact local search.
"""

import numpy as np
import pytest

from benchmarks.certify import CASES
from spm_sysid.core.fit.evaluator import StructureEvaluator
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.identify import identify_problem
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.options import SearchOptions
from spm_sysid.core.search.local import local_search
from spm_sysid.core.search.neighbourhood import MoveScreen

SPACE = TermSpace(ny=3, nu=3, degree=3, constant=True)  # 84 candidates


@pytest.fixture(scope="module")
def arm84(robot_arm):
    u, y = robot_arm
    h = len(y) // 2
    P = SPACE.regression_matrix(u[:h], y[:h])
    target = np.asarray(y[:h])[SPACE.max_lag:]
    return P, target


def _lstsq_sse(P: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    coef, *_ = np.linalg.lstsq(P[:, mask], target, rcond=None)
    r = target - P[:, mask] @ coef
    return float(r @ r)


@pytest.mark.parametrize("size", [1, 12, 30])
def test_every_move_has_the_sse_plain_least_squares_gives(arm84, size):
    P, target = arm84
    ev = StructureEvaluator(P, target, "aic")
    rng = np.random.default_rng(size)
    mask = np.zeros(ev.n_terms, dtype=bool)
    mask[rng.choice(ev.n_terms, size, replace=False)] = True
    allowed = np.ones(ev.n_terms, dtype=bool)
    drop, add, sse, base = MoveScreen(ev).sse(mask, allowed, ("remove", "add", "swap"))
    assert base == pytest.approx(_lstsq_sse(P, target, mask), rel=1e-9)
    k, out = size, ev.n_terms - size
    assert len(drop) == (k if k > 1 else 0) + out + k * out  # every move, none left out
    for i in rng.choice(len(drop), 60, replace=False):
        moved = mask.copy()
        if drop[i] >= 0:
            moved[drop[i]] = False
        if add[i] >= 0:
            moved[add[i]] = True
        assert moved.sum() == k + (add[i] >= 0) - (drop[i] >= 0)
        assert sse[i] == pytest.approx(_lstsq_sse(P, target, moved), rel=1e-8)


def test_moves_into_a_column_the_structure_reproduces_are_left_out(arm84):
    P, target = arm84
    P = np.column_stack([P, 2.0 * P[:, 3]])  # a last column twice column 3
    ev = StructureEvaluator(P, target, "aic")
    mask = np.zeros(ev.n_terms, dtype=bool)
    mask[[3, 10]] = True
    drop, add, _, _ = MoveScreen(ev).sse(mask, np.ones(ev.n_terms, dtype=bool),
                                        ("add", "swap"))
    last = ev.n_terms - 1
    assert not np.any((add == last) & (drop != 3))  # column 3 still in: dependent
    assert np.any((add == last) & (drop == 3))  # swapped for its twin: allowed
    dependent = mask.copy()
    dependent[last] = True
    assert MoveScreen(ev).sse(dependent, np.ones(ev.n_terms, dtype=bool), ("add",)) is None


def test_a_collinear_start_loses_the_terms_its_earlier_terms_reproduce(arm84):
    P, target = arm84
    twin = P[:, 3] - 0.5 * P[:, 10]  # reproduced by columns 3 and 10
    P = np.column_stack([P, twin, 3.0 * P[:, 20]])
    ev = StructureEvaluator(P, target, "bic")
    screen, allowed = MoveScreen(ev), np.ones(ev.n_terms, dtype=bool)
    mask = np.zeros(ev.n_terms, dtype=bool)
    mask[[3, 10, 20, 33, ev.n_terms - 2, ev.n_terms - 1]] = True
    assert screen.sse(mask, allowed, ("add",)) is None
    kept = screen.independent(mask)
    assert np.flatnonzero(kept).tolist() == [3, 10, 20, 33]  # the two later copies go
    assert screen.sse(kept, allowed, ("add",)) is not None
    assert np.array_equal(screen.independent(kept), kept)
    end, value, _ = screen.descend(mask, allowed, 500)  # the kick is not wasted
    assert np.isfinite(value) and value == pytest.approx(ev.cached_score(end), abs=1e-6)


def test_the_screened_descent_ends_where_the_exact_local_search_finds_no_better(arm84):
    P, target = arm84
    for criterion in ("aic", "bic"):
        ev = StructureEvaluator(P, target, criterion)
        allowed = np.ones(ev.n_terms, dtype=bool)
        start = np.zeros(ev.n_terms, dtype=bool)
        start[[0, 5, 40]] = True
        end, value, used = MoveScreen(ev).descend(start, allowed, 500)
        assert 1 < used < 500
        exact = ev.cached_score(end)
        assert value == pytest.approx(exact, abs=1e-6)
        again = local_search(ev.score, end, allowed, start_value=exact)
        assert again.steps == 0 and again.value == pytest.approx(exact, abs=1e-9)


def test_the_polish_at_84_candidates_is_reproducible_and_ends_at_a_local_optimum():
    u, y = CASES["dryer-0"]()
    problem = Problem.from_signals(u, y, SPACE)
    options = SearchOptions(criterion="bic", seed=3, auto_certify_time_limit=0,
                            selection="criterion")
    model = identify_problem(problem, options).model
    pol = model.metadata["polish"]
    assert identify_problem(problem, options).model.metadata["polish"] == pol
    assert pol["kicks"] >= 1 and pol["moves"] == ["remove", "add", "swap"]
    assert pol["value"] <= pol["ga_value"] and pol["stopped"] in ("restarts", "home", "budget")
    assert pol["structures"] <= pol["kicks"] + 1  # only promising ends scored exactly
    ev = problem.evaluator("bic")
    again = local_search(ev.score, problem.restrict(model.mask),
                         np.ones(ev.n_terms, dtype=bool))
    assert again.value >= model.criterion_value - 1e-9


def test_the_polish_reports_its_progress_as_the_phase_after_the_search():
    from spm_sysid.core.progress import PHASES
    from spm_sysid.core.search.local import POLISH_STEPS

    u, y = CASES["dryer-0"]()
    problem = Problem.from_signals(u, y, SPACE)
    options = SearchOptions(criterion="bic", seed=3, auto_certify_time_limit=0,
                            selection="criterion")
    records = []
    model = identify_problem(problem, options, progress=records.append).model
    phases = [p.phase for p in records]
    # 84 candidates: two searches (RESTART_TERMS), each a search then its polish, and
    # after the second the polishes from forward selection, from every term and from
    # the best ends' common terms (when two ends differ)
    runs = [k for k, p in enumerate(phases)
            if p == "search" and (k == 0 or phases[k - 1] != "search")]
    again = model.metadata["polish"]["restart"]
    assert len(runs) == 2 and again["kept"] in (
        "first", "second", "forward", "all_terms", "common")
    assert PHASES.index("search") + 1 == PHASES.index("polish")
    later = 3 + ("common" in again)
    for (a, b), polishes in (((runs[0], runs[1]), 1), ((runs[1], len(records)), later)):
        assert list(dict.fromkeys(phases[a:b])) == ["search", "polish"]
        polish = [p for p in records[a:b] if p.phase == "polish"]
        starts = [k for k, p in enumerate(polish) if p.step == 0 and p.total == 0]
        assert len(starts) == polishes and starts[0] == 0
        assert all(p.total in (0, POLISH_STEPS) and p.step <= POLISH_STEPS for p in polish)
        for s, e in zip(starts, [*starts[1:], len(polish)]):
            assert [p.step for p in polish[s:e]] == sorted(p.step for p in polish[s:e])
    first = [p.best for p in records[:runs[1]] if p.phase == "polish"]
    assert first == sorted(first, reverse=True)
    second = [p.best for p in records[runs[1]:]]  # the best so far: never the first's worse
    assert max(second) <= first[-1] + 1e-9 and second[-1] >= model.criterion_value - 1e-9
    assert records[-1].best_model() is not None  # a job stopped here keeps its best model


def test_large_spaces_rank_fewer_steps_as_each_step_costs_more(arm84, robot_arm):
    from spm_sysid.core.defaults import POLISH_STEP_WORK
    from spm_sysid.core.search.local import POLISH_STEPS

    P, target = arm84
    small = MoveScreen(StructureEvaluator(P, target, "aic"))  # 84 candidates
    assert all(small.step_budget(k) == POLISH_STEPS for k in (1, 20, 42, 83))
    rng = np.random.default_rng(0)
    large = MoveScreen(StructureEvaluator(rng.standard_normal((2000, 454)),
                                          rng.standard_normal(2000), "aic"))
    work = 455 * 100 * 354
    assert large.step_budget(100) == int(POLISH_STEPS * POLISH_STEP_WORK / work)
    assert 1 <= large.step_budget(227) <= large.step_budget(100) < POLISH_STEPS
    # 164 candidates, AIC: the ranked polish on a budget of its work, better than the GA
    u, y = robot_arm
    h = len(y) // 2
    problem = Problem.from_signals(u[:h], y[:h], TermSpace(ny=4, nu=4, degree=3))
    options = SearchOptions(criterion="aic", seed=1, auto_certify_time_limit=0,
                            selection="criterion")
    pol = identify_problem(problem, options).model.metadata["polish"]
    assert pol["moves"] == ["remove", "add", "swap"] and pol["budget"] < POLISH_STEPS
    assert pol["value"] < pol["ga_value"] - 1.0


def test_mid_size_spaces_are_searched_twice_and_the_better_kept():
    """84 candidates (more than RESTART_TERMS): a second GA and polish from another seed
    stream; the model is the better of the two and the answer says what each ended at.
    The paper's 44 candidates and validated selections stay one search."""
    from spm_sysid.core.jobs.single import _certificate_words

    u, y = CASES["dryer-0"]()
    problem = Problem.from_signals(u, y, SPACE)
    # seed 0 ends both searches at the same value, seed 1 the second worse (seeds 2 and 3
    # repeat seed 0's ends: measured 2026-12-08)
    for seed in (0, 1):
        options = SearchOptions(criterion="bic", seed=seed, auto_certify_time_limit=0,
                                selection="criterion")
        model = identify_problem(problem, options).model
        again = model.metadata["polish"]["restart"]
        ends = {k: again[k] for k in ("first", "second", "forward", "all_terms", "common")
                if k in again}
        assert len(ends) >= 4
        assert model.criterion_value == pytest.approx(min(ends.values()), abs=1e-9)
        assert ends[again["kept"]] == pytest.approx(min(ends.values()), abs=1e-9)
        # kept: the earliest of the best (a later start must do better to be kept)
        earlier = list(ends)[:list(ends).index(again["kept"])]
        assert all(ends[k] > ends[again["kept"]] + 1e-9 for k in earlier)
        assert model.criterion_value == pytest.approx(
            problem.evaluator("bic").score(problem.restrict(model.mask)[None, :])[0], abs=1e-6)
        words = _certificate_words(model.metadata)
        assert (f"a second GA and polish from another seed stream ended at "
                f"{again['second']:.2f}, the first at {again['first']:.2f}, the polish from "
                f"forward selection at {again['forward']:.2f}, the polish from every term at "
                f"{again['all_terms']:.2f}") in words
    small = Problem.from_signals(u, y, TermSpace())
    options = SearchOptions(criterion="bic", seed=0, auto_certify_time_limit=0,
                            selection="criterion")
    assert "restart" not in identify_problem(small, options).model.metadata["polish"]
    # a selection judged on held-out data is not the criterion's optimum: one search
    held_out = SearchOptions(criterion="bic", seed=0, selection="validated")
    assert "restart" not in identify_problem(problem, held_out).model.metadata["polish"]

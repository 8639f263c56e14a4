"""The simulation focus: structures judged by how they simulate, not by one-step error.

A structure is fitted by least squares, refined on its free-run error
(:func:`~spm_sysid.core.fit.refine.refine_simulation`) and scored by the
criterion with the free-run SSE in place of the one-step SSE
(:func:`simulation_value`). :class:`SimulationScorer` is that score, the one
scorer of both selections:

* :func:`select_for_simulation` (selection by the criterion): the candidates,
  then a local search around the best, the winner refined to convergence;
* :func:`validated_simulation` (validated selection): the candidates screened
  in-sample with short refinements, finalists per degree and size judged on
  held-out blocks, the chosen one refined and checked by the stability guard.
"""

from __future__ import annotations

import time

import numpy as np

from ..defaults import FINALISTS, FOLD_STEPS, PER_SIZE, SEARCH_STEPS, SHRINK_FACTORS, SIGNIFICANCE
from ..errors import DataError
from ..fit.criteria import Criterion
from ..fit.evaluator import key_mask, mask_key
from ..fit.lstsq import sse_floor
from ..fit.problem import Problem
from ..fit.refine import free_run_uncertainty, refine_simulation
from ..model.narx import NarxModel
from ..progress import Progress, ProgressFn
from ..search.local import SearchResult, local_search
from .validated import Scores, stress_check, sub_blocks

__all__ = ["FINALISTS", "FOLD_STEPS", "PER_SIZE", "SEARCH_STEPS", "SIGNIFICANCE",
           "SimulationScorer", "choose_nonlinear_or_linear", "linear_masks",
           "linear_structures", "paired_p_value",
           "select_for_simulation", "shrink_to_hold", "simulation_value",
           "validated_simulation"]

#: How a finalist's coefficients are estimated; each is judged on the held-out blocks
#: and the better one of each structure competes: least squares, or least squares
#: refined on the free-run error (which helps nonlinear structures most and on short
#: records can overfit).
ESTIMATORS = ("least squares", "refined")


def simulation_value(criterion: Criterion, sse: float, rows: int, mask: np.ndarray,
                     coefficients: np.ndarray, problem: Problem) -> float:
    """The criterion with the free-run SSE (standardised coefficients as for one-step).

    An SSE below rounding (:func:`~spm_sysid.core.fit.lstsq.sse_floor`) counts as the
    floor, as for one-step errors: exact fits score alike and the fewest terms win.
    """
    beta = np.zeros((1, problem.term_space.n_terms))
    y_norm = float(np.linalg.norm(problem.target)) * problem.y_scale or 1.0
    beta[0, mask] = coefficients * problem.column_norms[mask] / y_norm
    sse = max(sse, sse_floor(y_norm), 1e-300)
    v = float(criterion(np.array([sse]), rows, np.array([mask.sum()]), beta)[0])
    return v if np.isfinite(v) else np.inf


class SimulationScorer:
    """Structures scored by the criterion of their refined free-run error; cached.

    Parameters
    ----------
    problem : Problem
    criterion : Criterion
    steps : int or None
        Levenberg-Marquardt evaluations of a refinement from least squares (None:
        refine_simulation's own limit); a move of the local search is warm-started from the
        current structure's coefficients with :data:`SEARCH_STEPS` (from least
        squares with ``steps`` when that fails).
    max_terms : int
        Larger structures score +inf (0: no limit).
    notes : bool
        Keep the refinement's account in each model's metadata.
    progress, started
        ``refinement`` progress: structures refined, best value so far.

    Attributes
    ----------
    scored : dict
        Structure key (:func:`~spm_sysid.core.fit.evaluator.mask_key`) ->
        (value, refined model or None); +inf for one that cannot be fitted or
        whose simulation diverges on the estimation data.
    """

    def __init__(self, problem: Problem, criterion: Criterion, *, steps: int | None = None,
                 max_terms: int = 0, notes: bool = False, progress: ProgressFn | None = None,
                 started: float | None = None) -> None:
        self.problem, self.criterion = problem, criterion
        self.steps, self.max_terms, self.notes = steps, max_terms, notes
        self.report = progress or (lambda p: None)
        self.started = time.perf_counter() if started is None else started
        self.scored: dict[bytes, tuple[float, NarxModel | None]] = {}
        self.refinements = 0
        self.current: NarxModel | None = None  # the local search's current structure

    def __call__(self, mask: np.ndarray) -> float:
        """The structure's value (scored once; warm-started from :attr:`current`)."""
        key = mask_key(mask)
        if key in self.scored:
            return self.scored[key][0]
        problem = self.problem
        value, model = np.inf, None
        if mask.any() and not (mask & ~problem.usable).any() and not (
                self.max_terms and mask.sum() > self.max_terms):
            try:
                model = problem.model(mask)
            except ValueError:  # linearly dependent on this data
                model = None
        if model is not None:
            ref = self._refine(model)
            self.refinements += 1
            if ref.success and np.isfinite(ref.sse):
                model.coefficients = ref.coefficients
                value = simulation_value(self.criterion, ref.sse, problem.rows, mask,
                                         ref.coefficients, problem)
                if self.notes:
                    model.metadata = {"refinement": ref.message, "free_run_sse": ref.sse,
                                      "least_squares_free_run_sse": ref.sse_start}
            else:
                model = None
        self.scored[key] = (value, model)
        self.report(Progress("refinement", self.refinements, 0, self.best_value,
                             elapsed=time.perf_counter() - self.started))
        return value

    def _refine(self, model: NarxModel):
        u, y, segments = self.problem.u, self.problem.y, self.problem.segments
        start = self.current
        if start is not None:  # warm start: the neighbour's refined coefficients
            theta = dict(zip(start.term_indices, start.coefficients))
            ls = model.coefficients
            model.coefficients = np.array([theta.get(i, 0.0) for i in model.term_indices])
            ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
            if ref.success:
                return ref
            model.coefficients = ls
        steps = {} if self.steps is None else {"max_evaluations": self.steps}
        return refine_simulation(model, u, y, segments, **steps)

    @property
    def best_value(self) -> float:
        return min(v for v, _ in self.scored.values())

    def best_key(self) -> bytes:
        return min(self.scored, key=lambda k: self.scored[k][0])

    def search(self, candidates: np.ndarray, max_steps: int = 10) -> SearchResult | None:
        """Score the candidates, then remove or add one term at a time around the best.

        The terms a move may bring in: every usable term in spaces of at most 100,
        else the candidates' terms. None when no candidate simulates.
        """
        for mask in candidates:
            self(mask)
        best = self.best_key()
        if not np.isfinite(self.scored[best][0]):
            return None
        n = self.problem.term_space.n_terms
        self.current = self.scored[best][1]
        pool = self.problem.usable.copy() if n <= 100 else candidates.any(axis=0)

        def moved(mask: np.ndarray, value: float) -> None:
            self.current = self.scored[mask_key(mask)][1]

        return local_search(lambda masks: np.array([self(m) for m in masks]),
                            key_mask(best, n), pool, moves=("remove", "add"),
                            start_value=self.scored[best][0], max_steps=max_steps,
                            on_step=moved)


def select_for_simulation(
    problem: Problem, candidates: np.ndarray, criterion: Criterion, *,
    metadata: dict | None = None, max_passes: int = 10,
    progress: ProgressFn | None = None, started: float | None = None,
) -> NarxModel:
    """The structure and coefficients that simulate best, by an information criterion.

    Each candidate structure (rows of ``candidates``, masks over the whole term
    space, e.g. the GA's best by the one-step criterion) is fitted by least
    squares, refined on its free-run error
    (:func:`~spm_sysid.core.fit.refine.refine_simulation`) and scored by
    ``criterion`` with the free-run SSE in place of the one-step SSE (so AIC
    becomes ``N ln(SSE_sim / N) + 2k``). From the best, a local search
    (:func:`~spm_sysid.core.search.local.local_search`) removes or adds one term
    at a time (terms of the candidates; every usable term in spaces of at most
    100) while that lowers the simulation criterion. Structures whose
    simulation diverges on the estimation data are never returned.

    Raises
    ------
    DataError
        When every candidate's simulation diverges on the estimation data.
    """
    u, y, segments = problem.u, problem.y, problem.segments
    scorer = SimulationScorer(problem, criterion, notes=True, progress=progress,
                              started=started)
    found = scorer.search(candidates, max_steps=max_passes)
    if found is None:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    best = found.mask
    value, model = scorer.scored[mask_key(best)]
    # the search's moves ran a few Levenberg-Marquardt steps each: finish the winner's
    final = refine_simulation(model, u, y, segments)
    refinements = scorer.refinements + 1
    if final.success and final.sse < model.metadata["free_run_sse"]:
        model.coefficients = final.coefficients
        value = simulation_value(criterion, final.sse, problem.rows, best, final.coefficients,
                                 problem)
        model.metadata["free_run_sse"] = final.sse
    one_step = model.residuals(u, y, segments)
    model.mse = float(one_step @ one_step) / len(one_step)
    model.criterion, model.criterion_value = criterion.name, value
    model.n_samples = problem.n_samples
    model.uncertainty = free_run_uncertainty(model, u, y, segments)
    model.metadata = {**(metadata or {}), "simulation": {
        **model.metadata, "candidates": len(candidates), "refinements": refinements,
        "local_search_steps": found.steps,
        "criterion_meaning": f"{criterion.name.upper()} of the free-run simulation error "
                             "(SSE of the simulated output) on the estimation data"}}
    return model


def validated_simulation(problem, candidates, folds, crit, max_terms, report,
                         started) -> tuple[NarxModel, dict]:
    """Simulation focus, validated: screen in-sample, judge finalists on held-out blocks.

    1. every candidate, and the full linear ARX structure of every order in the
       space (:func:`linear_structures`), by the criterion of its free-run
       error after a short refinement on all estimation data
       (:class:`SimulationScorer`, at most :data:`SEARCH_STEPS` evaluations);
    2. finalists: for each highest degree (linear, quadratic, ...) the best
       screened structures of each size, up to :data:`FINALISTS` sizes spread
       over the range (the group's best always among them), and every linear
       ARX structure; each fold fits least squares on its rows (and refines
       that on its free-run error over its segments: both estimates compete)
       and simulates the held-out block; the errors are gathered per sub-block
       (:func:`~spm_sysid.core.select.validated.sub_blocks`), each a separate
       held-out estimate; a run that leaves the measured range rejects the
       structure;
    3. the choice (:func:`choose_nonlinear_or_linear`): the best linear finalist
       unless a nonlinear one simulates the held-out blocks better by more than
       the noise of that comparison (a one-sided paired test over the blocks,
       :data:`SIGNIFICANCE`); it is refined to convergence on all data and must
       pass the guard (:func:`~spm_sysid.core.select.validated.stress_check`),
       with its nonlinear terms shrunk if that is what it takes
       (:func:`shrink_to_hold`); otherwise the next.
    """
    u, y, segments = problem.u, problem.y, problem.segments
    scorer = SimulationScorer(problem, crit, steps=SEARCH_STEPS, max_terms=max_terms,
                              progress=report, started=started)
    linear = linear_structures(problem)
    for mask in list(candidates) + list(linear):
        scorer(mask)
    screened = scorer.scored
    finals = _finalists(screened, problem.term_space)
    keys = {key for _, key in finals}
    finals += [(screened[mask_key(m)][0], mask_key(m)) for m in linear
               if mask_key(m) not in keys and np.isfinite(screened[mask_key(m)][0])]
    if not finals:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    n = problem.term_space.n_terms
    scores = Scores()
    per_fold, estimator = [], []
    label = sub_blocks(problem, folds)
    for done, (_, key) in enumerate(finals):
        mask = key_mask(key, n)
        both = [_fold_free_run(problem, fold, mask) for fold in folds]
        rejected = False
        for j, how in enumerate(ESTIMATORS):
            values = _sub_block_mse([b[j] for b in both], label, len(folds))
            scores.masks.append(mask)
            per_fold.append(values)
            estimator.append(how)
            if all(np.isfinite(values)):
                scores.mean.append(float(np.mean(values)))
                scores.stderr.append(float(np.std(values, ddof=1) / np.sqrt(len(values))))
            else:
                scores.mean.append(np.inf)
                scores.stderr.append(np.inf)
                rejected = True
        scores.rejected += rejected
        report(Progress("refinement", done + 1, len(finals),
                        elapsed=time.perf_counter() - started))
    degree = np.array([len(t) for t in problem.term_space.terms])
    order, decision = choose_nonlinear_or_linear(scores, per_fold, degree)
    decision["estimator"] = estimator[order[0]] if order else None
    removed, reasons = scores.rejected, []
    linear_sse = _linear_free_run_sse(problem, scores, degree, screened)
    tried = set()
    for i in order:
        mask = scores.masks[i]
        if (mask_key(mask), estimator[i]) in tried:
            continue
        tried.add((mask_key(mask), estimator[i]))
        model = screened[mask_key(mask)][1]
        if estimator[i] == "least squares":  # as the held-out blocks judged it
            model.coefficients = problem.model(mask).coefficients
            final = None
            reason = stress_check(model, u, y, segments)
        else:
            start = model.coefficients
            final = refine_simulation(model, u, y, segments)
            if final.success and np.isfinite(final.sse):
                model.coefficients = final.coefficients
            reason = stress_check(model, u, y, segments)
            if reason and final.success:
                model.coefficients = start
                reason = stress_check(model, u, y, segments)
        shrunk = None
        if reason and degree[mask].max() > 1:
            shrunk = shrink_to_hold(model, u, y, segments, linear_sse)
            if shrunk is not None:
                reason = None
        if reason:
            removed += 1
            reasons.append(reason)
            continue
        e = model.measured(y, segments) - model.run(u, y, None, segments)[0]
        sse = float(e @ e)
        one_step = model.residuals(u, y, segments)
        model.mse = float(one_step @ one_step) / len(one_step)
        model.criterion = crit.name
        model.criterion_value = simulation_value(crit, sse, problem.rows, mask,
                                                 model.coefficients, problem)
        model.n_samples = problem.n_samples
        model.uncertainty = free_run_uncertainty(model, u, y, segments)
        model.metadata = {"simulation": {
            "estimator": estimator[i],
            "refinement": final.message if final is not None else "none: least squares "
                          "simulated the held-out blocks better",
            "free_run_sse": sse,
            **({"least_squares_free_run_sse": final.sse_start} if final is not None else {}),
            **({"shrunk_nonlinear_terms": shrunk} if shrunk is not None else {}),
            "criterion_meaning": f"{crit.name.upper()} of the free-run simulation error "
                                 "(SSE of the simulated output) on the estimation data"}}
        if i != order[0]:
            decision = {**decision, "fallback": "the chosen structure failed the guard; "
                        f"the next by the rule has {int(mask.sum())} terms"}
        return model, {"held_out_mse": scores.mean[i], "held_out_stderr": scores.stderr[i],
                       "candidates": len(candidates), "screened": len(screened),
                       "finalists": len(finals), "removed_by_guard": removed,
                       "linear_or_nonlinear": decision,
                       **({"guard_reasons": reasons} if reasons else {})}
    raise DataError(f"every finalist structure's simulation leaves the output's range off the "
                    f"estimation data ({removed} removed by the guard"
                    + (f": {reasons[0]}" if reasons else "") + ")")


def linear_structures(problem) -> list[np.ndarray]:
    """The full linear ARX structures of every order 1..max lag in the problem's space.

    Order k: the constant (when the space has it), ``y(t-1) .. y(t-k)`` and each
    input's first k lags (capped at the space's lags); only usable terms. These
    are what a user's one-line ``arx`` fit would give, so every one of them
    competes as a finalist.
    """
    return linear_masks(problem.term_space, problem.usable)


def linear_masks(term_space, usable: np.ndarray | None = None) -> list[np.ndarray]:
    """:func:`linear_structures` of a term space (only ``usable`` terms when given)."""
    ts = term_space
    lin = ts.linear
    index = {t: i for i, t in enumerate(ts.terms)}
    first = {}
    for source, lag in lin:
        first.setdefault(source, lag)
    top = max([ts.ny] + list(ts.nus))
    out, seen = [], set()
    for k in range(1, top + 1):
        mask = np.zeros(ts.n_terms, dtype=bool)
        if ts.constant:
            mask[index[()]] = True
        for j, (source, lag) in enumerate(lin):
            if lag - first[source] < k:
                mask[index[(j,)]] = True
        if usable is not None:
            mask &= usable
        key = mask_key(mask)
        if mask.any() and key not in seen:
            seen.add(key)
            out.append(mask)
    return out



def choose_nonlinear_or_linear(scores: Scores, per_fold: list[list[float]],
                               degree: np.ndarray) -> tuple[list[int], dict]:
    """The finalists in the order to try, and the account of the linear/nonlinear call.

    The best linear finalist (lowest mean held-out free-run MSE) is the default.
    A nonlinear finalist replaces it only when it simulates the held-out blocks
    better by more than the noise of that comparison: over the blocks, the log
    ratio ``ln(MSE_linear / MSE_nonlinear)`` has a positive mean with a one-sided
    paired t-test p-value below :data:`SIGNIFICANCE` (blocks differ a lot in
    level; the log ratio compares each block with itself). One nonlinear
    finalist is tested -- the fewest terms within one standard error of the
    best nonlinear one -- since testing each of many would pass one by chance.
    Without a linear finalist the plain one-SE rule (:meth:`Scores.order`) decides.
    """
    finite = [i for i, v in enumerate(scores.mean) if np.isfinite(v)]
    is_linear = {i: int(degree[scores.masks[i]].max()) <= 1 for i in finite}
    linear = [i for i in finite if is_linear[i]]
    if not linear:
        return scores.order(), {"choice": "nonlinear", "reason": "no linear finalist "
                                "simulated every held-out block"}
    lin = min(linear, key=lambda i: scores.mean[i])
    account = {"best_linear_terms": int(scores.masks[lin].sum()),
               "best_linear_held_out_mse": scores.mean[lin],
               "best_linear_held_out_stderr": scores.stderr[lin],
               "blocks": len(per_fold[lin]), "significance": SIGNIFICANCE}
    rest = sorted(finite, key=lambda i: scores.mean[i])
    nonlinear = [i for i in rest if not is_linear[i]]
    challenger = None
    if nonlinear and scores.mean[nonlinear[0]] < scores.mean[lin]:
        # the nonlinear finalist to test: the fewest terms within one SE of the best
        # nonlinear one (one test: testing every finalist would find a "winner" by chance)
        low = nonlinear[0]
        near = [i for i in nonlinear if scores.mean[i] <= scores.mean[low] + scores.stderr[low]
                and scores.mean[i] < scores.mean[lin]]
        challenger = min(near, key=lambda i: (int(scores.masks[i].sum()), scores.mean[i]))
        p = paired_p_value(per_fold[lin], per_fold[challenger])
        account.update(nonlinear_terms=int(scores.masks[challenger].sum()),
                       ratio=scores.mean[challenger] / scores.mean[lin], p_value=p)
        if p >= SIGNIFICANCE:
            challenger = None
    if challenger is not None:
        account["choice"] = "nonlinear"
        order = [challenger, lin] + [i for i in rest if i not in (challenger, lin)]
    else:
        account["choice"] = "linear"
        order = [lin] + [i for i in rest if i != lin and is_linear[i]] + nonlinear
    return order, account


def paired_p_value(reference: list[float], other: list[float]) -> float:
    """One-sided paired t-test over blocks that ``other``'s errors are lower than ``reference``'s.

    On the log ratio of each block's two errors (blocks differ a lot in level; the
    ratio compares each block with itself); errors below 1e-12 of the largest count
    as that floor (a noise-free fit). 0 or 1 when the ratios do not vary.
    """
    from scipy import stats

    # errors a million millions below the larger are rounding: a perfect fit is not
    # "noisy" because 1e-30 and 1e-33 differ by a factor of a thousand
    floor = max(1e-300, 1e-12 * float(np.max(np.r_[reference, other])))
    d = np.log(np.maximum(reference, floor)) - np.log(np.maximum(other, floor))
    if len(d) < 2 or np.ptp(d) == 0:
        return 0.0 if np.all(d > 0) else 1.0
    return float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)


def _linear_free_run_sse(problem, scores: Scores, degree: np.ndarray,
                         screened: dict) -> float:
    """In-sample free-run SSE of the linear finalists' best screened model (inf: none)."""
    best = np.inf
    u, y, segments = problem.u, problem.y, problem.segments
    for mask, mean in zip(scores.masks, scores.mean):
        model = screened[mask_key(mask)][1]
        if np.isfinite(mean) and degree[mask].max() <= 1 and model is not None:
            yhat, at = model.run(u, y, None, segments)
            if at is None:
                e = model.measured(y, segments) - yhat
                best = min(best, float(e @ e))
    return best



def shrink_to_hold(model: NarxModel, u, y, segments, linear_sse: float) -> float | None:
    """Shrink the nonlinear terms that drive a divergence until the model holds; the factor.

    The nonlinear coefficients are scaled by each of :data:`SHRINK_FACTORS` in
    turn (the linear ones kept: they carry the dynamics); the first factor
    whose model passes the guard and still simulates the estimation data better
    than the best linear finalist (``linear_sse``) is kept. None (model unchanged) when none does.
    """
    degree = np.array([len(model.term_space.terms[i]) for i in model.term_indices])
    nonlinear = degree > 1
    start = model.coefficients.copy()
    for factor in SHRINK_FACTORS:
        model.coefficients = np.where(nonlinear, start * factor, start)
        if stress_check(model, u, y, segments) is not None:
            continue
        e = model.measured(y, segments) - model.run(u, y, None, segments)[0]
        if np.all(np.isfinite(e)) and float(e @ e) < linear_sse:
            return factor
    model.coefficients = start
    return None


def _finalists(screened: dict, term_space) -> list[tuple[float, bytes]]:
    """The best screened structures of each size (:data:`PER_SIZE`), sizes spread, by degree.

    Structures are grouped by their highest degree (linear, quadratic, ...):
    in-sample, a nonlinear structure nearly always beats a linear one of the
    same size, yet off the estimation data the linear one often simulates
    better, so each group sends its own finalists to the held-out blocks. In
    each group at most :data:`FINALISTS` sizes, spread on a log scale (small
    models are cheap to overlook and often what the data support), the group's
    best among them.
    """
    n_terms = term_space.n_terms
    degree = np.array([len(t) for t in term_space.terms])
    groups: dict[int, dict[int, list[tuple[float, bytes]]]] = {}
    for key, (value, _) in screened.items():
        if np.isfinite(value):
            mask = key_mask(key, n_terms)
            by_size = groups.setdefault(int(degree[mask].max()), {})
            by_size.setdefault(int(mask.sum()), []).append((value, key))
    out = []
    for by_size in groups.values():
        sizes = sorted(by_size)
        if len(sizes) > FINALISTS:
            best_size = min(sizes, key=lambda k: min(by_size[k])[0])
            targets = np.geomspace(sizes[0], sizes[-1], FINALISTS - 1)
            spread = {min(sizes, key=lambda k: abs(np.log(k) - np.log(t))) for t in targets}
            sizes = sorted(spread | {best_size})
        out += [item for k in sizes for item in sorted(by_size[k])[:PER_SIZE]]
    return sorted(out)


def _fold_free_run(problem, fold, mask: np.ndarray):
    """Held-out free-run squared errors of the structure fitted on the fold.

    Two runs: least squares on the fold's rows, then refined from there on the
    free-run error of the fold's segments (:data:`FOLD_STEPS` evaluations). Each
    is ``(samples, squared errors)`` of the held-out rows, ``"diverged"`` when the
    run left the range, or None when the structure cannot be fitted.
    """
    u, y = problem.u, problem.y
    try:
        fit = problem.fit(mask, rows=fold.train)
    except ValueError:
        return None, None
    model = problem.model(mask, fit)
    lag = problem.term_space.max_lag
    at = np.concatenate([np.arange(a + lag, b) for a, b in fold.held_out])

    def held_out():
        yhat, diverged = model.run(u, y, None, fold.held_out)
        if diverged is not None:
            return "diverged"
        e = model.measured(y, fold.held_out) - yhat
        return at, e * e

    least_squares = held_out()
    ref = refine_simulation(model, u, y, fold.train_segments, max_evaluations=FOLD_STEPS)
    if not (ref.success and np.isfinite(ref.sse)):
        return least_squares, least_squares
    model.coefficients = ref.coefficients
    return least_squares, held_out()


def _sub_block_mse(runs, label: np.ndarray, n_sub: int) -> list[float]:
    """Each sub-block's held-out MSE over the folds' runs (inf: a run diverged; NaN: unfit)."""
    if any(r is None for r in runs):
        return [np.nan] * n_sub
    if any(isinstance(r, str) for r in runs):
        return [np.inf] * n_sub
    sse, count = np.zeros(n_sub), np.zeros(n_sub)
    for at, sq in runs:
        ids = label[at]
        np.add.at(sse, ids, sq)
        np.add.at(count, ids, 1)
    return list(np.where(count > 0, sse / np.maximum(count, 1), np.nan))

"""From a record to a fitted model: the identification pipeline, written once.

::

    signals + term space --Problem.from_signals--> Problem (checked, scaled, built once)
        --evaluator--> GA with SPM (run_ga) --> [certification] --> structure
        --focus prediction--> least squares (Problem.model)
        --focus simulation--> refined on the free-run error (select_for_simulation)

``identify(u=..., y=...)`` is the public entry; :func:`identify_problem` is the
same on a problem already built (a study's runs share one problem per process,
so a study run is exactly the computation ``identify`` does).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..blas import one_blas_thread
from ..errors import DataError
from ..progress import Progress, ProgressFn
from .criteria import Criterion, get_criterion
from .ga import GAConfig, GAResult, GenerationStats, run_ga
from .model import NarxModel
from .problem import Problem, check_samples, validate_signals
from .refine import free_run_uncertainty, refine_simulation
from .search import local_search
from .selection import Scores, blocked_folds, candidate_structures, cv_scores, stress_check
from .terms import TermSpace

__all__ = ["FOCUS", "SELECTION", "IdentificationResult", "check_samples", "identify",
           "identify_problem", "select_for_simulation", "validate_signals"]

#: What a model is selected and fitted for.
FOCUS = ("prediction", "simulation")

#: Levenberg-Marquardt evaluations per move of the simulation-focused local search
#: (warm-started from the neighbour; the winner is then refined to convergence).
SEARCH_STEPS = 30


@dataclass
class IdentificationResult:
    """A fitted model, the search that produced it, and the problem it was fitted on."""

    model: NarxModel
    ga: GAResult
    problem: Problem | None = None


def identify(
    *,
    u: np.ndarray,
    y: np.ndarray,
    term_space: TermSpace | None = None,
    criterion: str | Criterion | Callable[..., float] = "aic",
    ga: GAConfig | None = None,
    seed: int | None = None,
    callback: Callable[[GenerationStats], bool | None] | None = None,
    segments: list[tuple[int, int]] | None = None,
    focus: str = "prediction",
    shortlist: int = 20,
    certify_time_limit: float | None = None,
    selection: str = "auto",
    max_terms: int = 0,
    polish: bool = True,
    auto_certify_time_limit: float = 10.0,
    progress: ProgressFn | None = None,
) -> IdentificationResult:
    """Select a NARX structure with the SPM-GA and fit it.

    Parameters
    ----------
    u : ndarray, shape (n,) or (n, m)
        Input samples (one column per input of the term space).
    y : ndarray, shape (n,)
        Output samples, equally spaced (within each segment).
    term_space : TermSpace, optional
        Candidate terms; default: the paper's (ny=4, nu=4, degree 2, delay 1).
    criterion : str, Criterion or callable
        ``"aic"``, ``"bic"``, ``"pmic2"`` or a user's ``f(sse, n, k, coefficients)``.
    ga : GAConfig, optional
        GA settings; default: the paper's (population 200, 300 generations, SPM 0.15).
    seed : int, optional
        Makes the run reproducible.
    callback : callable, optional
        Called with each generation's statistics; returning ``False`` stops the
        search (see :func:`spm_sysid.core.narx.ga.run_ga`).
    segments : list of (start, stop), optional
        Contiguous parts of the record (``[start, stop)`` indices, e.g. from
        :func:`spm_sysid.core.narx.segments.find_segments`): regression rows are built
        inside each and fitted together, never across a gap. Segments no longer
        than the largest lag are skipped. Default: the whole record.
    focus : {"prediction", "simulation"}
        ``prediction`` (the paper's): the GA's best structure, least squares.
        ``simulation``: see :func:`select_for_simulation` -- the structure and
        coefficients that simulate best, by the same criterion computed on the
        free-run error.
    shortlist : int
        With ``focus="simulation"``: how many of the GA's best structures are
        refined and compared.
    certify_time_limit : float, optional
        After the GA, prove its best structure the optimum of the whole term
        space by branch and bound (:mod:`spm_sysid.core.narx.certify`; AIC and
        BIC), within this many seconds; the result is in
        ``model.metadata["certificate"]`` (``optimal``, or ``limit`` with the
        lower bound and gap, or ``refused`` with the reason). A better structure
        found on the way replaces the GA's.
    selection : {"auto", "criterion", "validated"}
        How the structure is chosen: by the criterion on the estimation data
        (the paper's), or by its error on held-out blocks of the estimation
        data (:mod:`spm_sysid.core.narx.selection`; the final model is fitted
        on all of it). ``auto``: validated for the simulation focus, and for the
        prediction focus when there are fewer than 10 rows per candidate term.
    max_terms : int
        Structures of more terms are not selected (0: no limit).
    polish : bool
        After the GA, a local search from its best structure (one term added,
        removed or swapped while that improves the criterion), then up to
        :data:`POLISH_KICKS` kicks (4 to 11 terms flipped, a cheap add/remove
        descent, and the full search from the promising ones); at most
        :data:`POLISH_STRUCTURES` structures scored (fewer for structures of
        more than :data:`POLISH_TERMS` terms), so the result does not depend on
        the machine's speed. ``model.metadata["polish"]`` says
        what it changed.
    auto_certify_time_limit : float
        When the structure is the criterion's choice (focus prediction,
        selection ``criterion``), the criterion is AIC, AICc or BIC and the space
        has at most :data:`AUTO_CERTIFY_TERMS` usable terms, certify the result
        within this many seconds even without ``certify_time_limit`` (0: off).
    progress : callable, optional
        Called with :class:`~spm_sysid.core.progress.Progress` records (search,
        certification, refinement).

    Notes
    -----
    u and y are scaled internally by powers of two (exact), so data of any
    magnitude identify alike; coefficients and criteria are in the user's units.
    Candidate terms whose regressor is zero on all rows (e.g. every term with u
    when the input is zero) are left out of the search, and the result says so
    (``model.metadata["excluded_zero_terms"]``); so are terms whose regressor is
    proportional to an earlier term's (every lag of a constant input but the
    first; the input's terms when the input equals the output):
    ``model.metadata["excluded_duplicate_terms"]`` maps each to the term it repeats.
    """
    problem = Problem.from_signals(u, y, term_space, segments)
    return identify_problem(problem, criterion=criterion, ga=ga, seed=seed, callback=callback,
                            focus=focus, shortlist=shortlist,
                            certify_time_limit=certify_time_limit, selection=selection,
                            max_terms=max_terms, polish=polish,
                            auto_certify_time_limit=auto_certify_time_limit, progress=progress)


#: How a structure is chosen (see :mod:`spm_sysid.core.narx.selection`).
SELECTION = ("auto", "criterion", "validated")

#: ``auto`` validates the prediction focus too when there are fewer rows than this many
#: per usable candidate term (where an in-sample criterion can overfit badly).
AUTO_ROWS_PER_TERM = 10

#: A held-out error this many times the in-sample error is reported as overfitting.
OVERFIT_RATIO = 3.0

#: Structures the polish after the GA may score (a count, not seconds: the same seed
#: gives the same result on any machine).
POLISH_STRUCTURES = 50_000
#: Structures of more terms than this cost more to fit (about k^2): the polish of a
#: structure of k terms scores at most POLISH_STRUCTURES * (POLISH_TERMS / k)^2 of them,
#: so a large model's polish does not take many times its GA's time.
POLISH_TERMS = 20
#: Kicks of the iterated local search after the first local optimum (within the budget).
POLISH_KICKS = 1000
#: Terms a kick flips: from POLISH_FLIPS[0] to POLISH_FLIPS[1] - 1 (the GA's best and the
#: optimum typically differ in 8-11 terms when the GA misses: a kick must reach that far).
POLISH_FLIPS = (4, 12)
#: A kicked structure whose add/remove descent ends within this of the best so far is
#: searched with swaps too (swaps cost k (n - k) structures a step: only for the promising).
POLISH_SLACK = 2.0

#: Spaces of at most this many usable terms are certified after the GA by default
#: (``auto_certify_time_limit``).
AUTO_CERTIFY_TERMS = 120


@one_blas_thread()
def identify_problem(
    problem: Problem,
    *,
    criterion: str | Criterion | Callable[..., float] = "aic",
    ga: GAConfig | None = None,
    seed: int | None = None,
    callback: Callable[[GenerationStats], bool | None] | None = None,
    focus: str = "prediction",
    shortlist: int = 20,
    certify_time_limit: float | None = None,
    selection: str = "auto",
    max_terms: int = 0,
    check_data: bool = True,
    polish: bool = True,
    auto_certify_time_limit: float = 10.0,
    progress: ProgressFn | None = None,
    started: float | None = None,
) -> IdentificationResult:
    """:func:`identify` on a problem already built (see there for the parameters).

    ``started`` is ``time.perf_counter()`` at the job's start (progress reports
    count their seconds from it; default: now). ``check_data``: run the data
    check (:mod:`spm_sysid.core.narx.excitation`) first; its warnings go into
    ``model.metadata["warnings"]``.
    """
    crit = get_criterion(criterion)
    if focus not in FOCUS:
        raise ValueError(f"focus must be one of {', '.join(FOCUS)}, got {focus!r}")
    if selection not in SELECTION:
        raise ValueError(f"selection must be one of {', '.join(SELECTION)}, got {selection!r}")
    started = time.perf_counter() if started is None else started
    report = progress or (lambda p: None)
    ga = ga or GAConfig()
    warnings: list[str] = []
    data_check = None
    if check_data:
        from .excitation import check_problem

        data_check = check_problem(problem)
        warnings += data_check.warnings
    evaluator = problem.evaluator(crit, max_terms=max_terms)

    def on_generation(stats: GenerationStats):
        report(Progress("search", stats.generation, ga.generations, stats.best,
                        stats.evaluations, elapsed=time.perf_counter() - started))
        return None if callback is None else callback(stats)

    result = run_ga(evaluator, ga, seed=seed, callback=on_generation)
    if not np.isfinite(result.best_score):
        raise DataError(
            "no structure could be fitted: every structure the search tried has linearly "
            "dependent regressors on this data (repeated or constant signals?)"
            + (f", or more than max_terms = {max_terms} terms" if max_terms else "")
        )
    polished = _polish(problem, evaluator, result) if polish else None
    mode, note = _selection_mode(selection, focus, problem)
    folds = blocked_folds(problem)
    if mode == "validated" and not folds:
        mode, note = "criterion", "the record is too short for held-out blocks"
    certificate = None
    if certify_time_limit is None and auto_certify_time_limit > 0:
        from .certify import CERTIFIABLE

        if (mode == "criterion" and focus == "prediction" and crit.name in CERTIFIABLE
                and problem.usable.sum() <= AUTO_CERTIFY_TERMS):
            certify_time_limit = auto_certify_time_limit
    if certify_time_limit is not None:
        certificate = _certify_search(problem, evaluator, result, crit, certify_time_limit,
                                      report, started)
    result.best_mask = problem.expand(result.best_mask)
    excluded = problem.excluded_terms()
    info = {
        "ga": ga.to_dict(),
        "seed": seed,
        "generations_run": len(result.history) - 1,
        "first_best_generation": result.first_best_generation,
        "evaluations": result.evaluations,
        "search_seconds": round(result.elapsed, 4),
        "focus": focus,
        **({"max_terms": max_terms} if max_terms else {}),
        **({"polish": polished} if polished is not None else {}),
        **({"excluded_zero_terms": excluded["zero"]} if excluded["zero"] else {}),
        **({"excluded_duplicate_terms": excluded["duplicate"]} if excluded["duplicate"]
           else {}),
        **({"certificate": certificate} if certificate is not None else {}),
        **({"data_check": data_check.to_dict()} if data_check is not None else {}),
    }
    simulate = focus == "simulation"
    chosen = None
    if mode == "validated":
        model, chosen = _select_validated(problem, evaluator, folds, crit, shortlist,
                                          max_terms, simulate, report, started)
        model.metadata = {**info, **model.metadata}
    elif simulate:
        candidates = problem.expand(evaluator.ranked(shortlist))
        model = select_for_simulation(problem, candidates, crit, metadata=info,
                                      progress=report, started=started)
    else:
        model = problem.model(result.best_mask, criterion=crit.name,
                              criterion_value=result.best_score, metadata=info)
    model.metadata["selection"] = _generalisation(problem, folds, model, mode, note, simulate,
                                                  chosen)
    warnings += _overfit_warnings(problem, model)
    if warnings:
        model.metadata["warnings"] = warnings
    return IdentificationResult(model=model, ga=result, problem=problem)


def _polish(problem: Problem, evaluator, result: GAResult) -> dict:
    """Local search from the GA's best (in place); what it did, for the document."""
    from .search import local_search

    ga_value = float(result.best_score)
    if not np.isfinite(ga_value):
        return {"ga_value": None, "value": None, "steps": 0, "structures": 0}
    n = problem.usable.sum()
    k = int(result.best_mask.sum())
    budget = min(POLISH_STRUCTURES, int(POLISH_STRUCTURES * (POLISH_TERMS / max(k, 1)) ** 2))
    # swaps are k (n - k) neighbours a step: in large spaces only additions and removals
    moves = ("remove", "add", "swap") if k * (n - k) <= budget // 4 else ("remove", "add")
    allowed = np.ones(evaluator.n_terms, dtype=bool)
    res = local_search(evaluator.score, result.best_mask, allowed, moves=moves,
                       start_value=ga_value, max_scored=budget)
    best_mask, best_value, steps, scored = res.mask, float(res.value), res.steps, res.scored
    # Iterated local search: the GA's best is usually a local optimum of single-term moves;
    # kick it (flip several terms), descend cheaply (additions and removals), and search
    # the promising ones with swaps too, keeping the best, within the budget. The kicks
    # are drawn from the structure itself, so the polish is reproducible.
    rng = np.random.default_rng(zlib.crc32(np.packbits(result.best_mask).tobytes()))
    usable = np.flatnonzero(problem.usable) if len(problem.usable) == evaluator.n_terms \
        else np.arange(evaluator.n_terms)
    cheap = ("remove", "add")
    low, high = POLISH_FLIPS[0], min(POLISH_FLIPS[1], len(usable) // 2 + 1)
    kicks = 0
    while kicks < POLISH_KICKS and scored < budget and high > low:
        kicks += 1
        start = best_mask.copy()
        flip = rng.choice(usable, size=int(rng.integers(low, high)), replace=False)
        start[flip] = ~start[flip]
        if not start.any():
            continue
        r = local_search(evaluator.score, start, allowed, moves=cheap,
                         max_scored=budget - scored)
        scored += r.scored
        if moves != cheap and r.value < best_value + POLISH_SLACK:
            r = local_search(evaluator.score, r.mask, allowed, moves=moves,
                             start_value=r.value, max_scored=budget - scored)
            scored += r.scored
        if r.value < best_value - 1e-9:
            best_mask, best_value, steps = r.mask, float(r.value), steps + r.steps
    if best_value < ga_value:
        result.best_mask, result.best_score = best_mask.copy(), best_value
    return {"ga_value": ga_value, "value": float(result.best_score), "steps": steps,
            "structures": scored, "kicks": kicks, "moves": list(moves),
            "stopped": "budget" if scored >= budget else res.stopped, "budget": budget}


def _selection_mode(selection: str, focus: str, problem: Problem) -> tuple[str, str]:
    """``criterion`` or ``validated``, and why (for the document)."""
    if selection != "auto":
        return selection, "as asked"
    if focus == "simulation":
        return "validated", "auto: the simulation focus is always validated"
    per_term = problem.rows / max(int(problem.usable.sum()), 1)
    if per_term < AUTO_ROWS_PER_TERM:
        return "validated", (f"auto: {per_term:.1f} rows per candidate term (fewer than "
                             f"{AUTO_ROWS_PER_TERM}): an in-sample criterion could overfit")
    return "criterion", f"auto: {per_term:.1f} rows per candidate term"


#: Structure sizes judged on held-out blocks after the in-sample screening (simulation),
#: and structures of each size.
FINALISTS = 8
PER_SIZE = 2

#: Levenberg-Marquardt evaluations of a fold's fit (from least squares on its rows).
FOLD_STEPS = 100


def _select_validated(problem, evaluator, folds, crit, shortlist, max_terms, simulate,
                      report, started) -> tuple[NarxModel, dict]:
    """Validated selection (see :mod:`spm_sysid.core.narx.selection`); model and record."""
    from .orders import forward_selection_path

    limit = min(60, max(1, problem.rows // AUTO_ROWS_PER_TERM))
    degree = np.array([len(t) for t in problem.term_space.terms])[problem.usable]

    def forward() -> np.ndarray:
        # forward selection over all terms and, below the space's degree, over the terms
        # of each lower degree: simpler models the GA may never visit
        paths = [forward_selection_path(evaluator, max_terms=limit)]
        for d in range(1, problem.term_space.degree):
            lower = degree <= d
            if lower.any():
                paths.append(forward_selection_path(evaluator, max_terms=min(limit, int(
                    lower.sum())), allowed=lower))
        return np.concatenate([p for p in paths if len(p)]) if any(len(p) for p in paths) \
            else np.zeros((0, evaluator.n_terms), dtype=bool)

    candidates = candidate_structures(problem, evaluator, shortlist, forward=forward)
    # structures of more than one term per AUTO_ROWS_PER_TERM rows are not judged: the
    # warning threshold of an overfit (and max_terms, when smaller)
    cap = min(limit, max_terms) if max_terms else limit
    candidates = candidates[candidates.sum(axis=1) <= cap]
    if not len(candidates):
        raise DataError(f"no candidate structure of at most {cap} terms could be fitted")
    if simulate:
        return _validated_simulation(problem, candidates, folds, crit, max_terms, report,
                                     started)
    scores = cv_scores(problem, folds, candidates, simulate=False)
    report(Progress("refinement", len(candidates), len(candidates),
                    elapsed=time.perf_counter() - started))
    i = scores.best()
    if i is None:
        raise DataError("no candidate structure could be fitted on the held-out folds")
    mask = scores.masks[i]
    model = problem.model(mask, criterion=crit.name,
                          criterion_value=evaluator.cached_score(problem.restrict(mask)))
    return model, {"held_out_mse": scores.mean[i], "held_out_stderr": scores.stderr[i],
                   "candidates": len(candidates)}


def _validated_simulation(problem, candidates, folds, crit, max_terms, report,
                          started) -> tuple[NarxModel, dict]:
    """Simulation focus, validated: screen in-sample, judge finalists on held-out blocks.

    1. every candidate by the criterion of its free-run error after a short
       refinement on all estimation data;
    2. finalists: for each highest degree (linear, quadratic, ...) the best
       screened structures of each size, up to :data:`FINALISTS` sizes spread
       over the range (the group's best always among them) -- the held-out
       blocks decide how large and how nonlinear a model the data support;
       each fold fits least squares on its rows, refines on its free-run
       error over its segments, and simulates the held-out block; a
       run that leaves the measured range rejects the structure;
    3. the chosen (fewest terms within one standard error of the best held-out
       error) is refined to convergence on all data and must pass the guard
       (:func:`~spm_sysid.core.narx.selection.stress_check`); otherwise the next.
    """
    u, y, segments = problem.u, problem.y, problem.segments
    screened = _screen_in_sample(problem, candidates, crit, max_terms, report, started,
                                 search=False)
    finals = _finalists(screened, problem.term_space)
    if not finals:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    n = problem.term_space.n_terms
    scores = Scores()
    for _, key in finals:
        mask = np.unpackbits(np.frombuffer(key, dtype=np.uint8))[:n].astype(bool)
        values = [_fold_free_run(problem, fold, mask) for fold in folds]
        scores.masks.append(mask)
        if all(np.isfinite(values)):
            scores.mean.append(float(np.mean(values)))
            scores.stderr.append(float(np.std(values, ddof=1) / np.sqrt(len(values))))
        else:
            scores.mean.append(np.inf)
            scores.stderr.append(np.inf)
            scores.rejected += 1
        report(Progress("refinement", len(scores.masks), len(finals),
                        elapsed=time.perf_counter() - started))
    removed, reasons = scores.rejected, []
    for i in scores.order():
        mask = scores.masks[i]
        model = screened[np.packbits(mask).tobytes()][1]
        start = model.coefficients
        final = refine_simulation(model, u, y, segments)
        if final.success and np.isfinite(final.sse):
            model.coefficients = final.coefficients
        reason = stress_check(model, u, y, segments)
        if reason and final.success:
            model.coefficients = start
            reason = stress_check(model, u, y, segments)
        if reason:
            removed += 1
            reasons.append(reason)
            continue
        e = model.measured(y, segments) - model.run(u, y, None, segments)[0]
        sse = float(e @ e)
        one_step = model.residuals(u, y, segments)
        model.mse = float(one_step @ one_step) / len(one_step)
        model.criterion = crit.name
        model.criterion_value = _simulation_value(crit, sse, problem.rows, mask,
                                                  model.coefficients, problem)
        model.n_samples = problem.n_samples
        model.uncertainty = free_run_uncertainty(model, u, y, segments)
        model.metadata = {"simulation": {
            "refinement": final.message, "free_run_sse": sse,
            "least_squares_free_run_sse": final.sse_start,
            "criterion_meaning": f"{crit.name.upper()} of the free-run simulation error "
                                 "(SSE of the simulated output) on the estimation data"}}
        return model, {"held_out_mse": scores.mean[i], "held_out_stderr": scores.stderr[i],
                       "candidates": len(candidates), "screened": len(screened),
                       "finalists": len(finals), "removed_by_guard": removed,
                       **({"guard_reasons": reasons} if reasons else {})}
    raise DataError(f"every finalist structure's simulation leaves the output's range off the "
                    f"estimation data ({removed} removed by the guard"
                    + (f": {reasons[0]}" if reasons else "") + ")")


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
            mask = np.unpackbits(np.frombuffer(key, dtype=np.uint8))[:n_terms].astype(bool)
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


def _screen_in_sample(problem, candidates, crit, max_terms, report, started,
                      search: bool = True) -> dict:
    """Structure key -> (criterion of the free-run error after a short refinement, model).

    The candidates, then (with ``search``) a local search (one term removed or
    added) around the best.
    """
    u, y, segments = problem.u, problem.y, problem.segments
    scored: dict[bytes, tuple[float, NarxModel | None]] = {}
    current: list[NarxModel | None] = [None]

    def one(mask: np.ndarray) -> float:
        key = np.packbits(mask).tobytes()
        if key in scored:
            return scored[key][0]
        value, model = np.inf, None
        if mask.any() and not (mask & ~problem.usable).any() and not (
                max_terms and mask.sum() > max_terms):
            try:
                model = problem.model(mask)
            except ValueError:  # linearly dependent on this data
                model = None
        if model is not None:
            start = current[0]
            if start is not None:  # warm start: the neighbour's refined coefficients
                theta = dict(zip(start.term_indices, start.coefficients))
                ls = model.coefficients
                model.coefficients = np.array([theta.get(i, 0.0) for i in model.term_indices])
                ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
                if not ref.success:
                    model.coefficients = ls
                    ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
            else:
                ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
            if ref.success and np.isfinite(ref.sse):
                model.coefficients = ref.coefficients
                value = _simulation_value(crit, ref.sse, problem.rows, mask, ref.coefficients,
                                          problem)
            else:
                model = None
        scored[key] = (value, model)
        report(Progress("refinement", len(scored), 0,
                        min(v for v, _ in scored.values()),
                        elapsed=time.perf_counter() - started))
        return value

    for mask in candidates:
        one(mask)
    best = min(scored, key=lambda k: scored[k][0])
    if search and np.isfinite(scored[best][0]):
        n = problem.term_space.n_terms
        start = np.unpackbits(np.frombuffer(best, dtype=np.uint8))[:n].astype(bool)
        current[0] = scored[best][1]
        pool = problem.usable.copy() if n <= 100 else candidates.any(axis=0)

        def moved(mask: np.ndarray, value: float) -> None:
            current[0] = scored[np.packbits(mask).tobytes()][1]

        local_search(lambda masks: np.array([one(m) for m in masks]), start, pool,
                     moves=("remove", "add"), start_value=scored[best][0], max_steps=10,
                     on_step=moved)
    return scored


def _fold_free_run(problem, fold, mask: np.ndarray) -> float:
    """Held-out free-run MSE of the structure fitted and refined on the fold (inf: diverged)."""
    u, y = problem.u, problem.y
    try:
        fit = problem.fit(mask, rows=fold.train)
    except ValueError:
        return np.nan
    model = problem.model(mask, fit)
    ref = refine_simulation(model, u, y, fold.train_segments, max_evaluations=FOLD_STEPS)
    if ref.success and np.isfinite(ref.sse):
        model.coefficients = ref.coefficients
    yhat, at = model.run(u, y, None, fold.held_out)
    if at is not None:
        return np.inf
    e = model.measured(y, fold.held_out) - yhat
    return float(np.mean(e * e))


def _generalisation(problem, folds, model, mode, note, simulate, chosen) -> dict:
    """How the structure was chosen and how it does on held-out data (the document's)."""
    what = "free-run" if simulate else "one-step"
    out = {"method": mode, "note": note, "what": what, "folds": len(folds)}
    if chosen is None and folds:
        sc = cv_scores(problem, folds, [model.mask], simulate)
        chosen = {"held_out_mse": sc.mean[0], "held_out_stderr": sc.stderr[0]}
    if chosen:
        out.update({k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                    for k, v in chosen.items()})
    if simulate:
        sse = (model.metadata.get("simulation") or {}).get("free_run_sse")
        in_sample = None if sse is None else sse / problem.rows
    else:
        in_sample = model.mse
    out["in_sample_mse"] = in_sample
    held = out.get("held_out_mse")
    out["ratio"] = (held / in_sample if held is not None and in_sample else None)
    return out


def _overfit_warnings(problem, model) -> list[str]:
    """Warnings when the model may fit noise: its size, its held-out error."""
    out = []
    k, rows = len(model.term_indices), problem.rows
    if k > rows / 10:
        out.append(f"{k} terms from {rows} rows (more than one term per 10 rows): the model "
                   "may fit noise; prefer BIC or AICc, max_terms, fewer lags, or "
                   "selection: validated")
    sel = model.metadata.get("selection") or {}
    ratio = sel.get("ratio")
    if ratio is not None and ratio > OVERFIT_RATIO:
        out.append(f"its {sel['what']} error on held-out blocks is {ratio:.1f} times its error "
                   "on the data it was fitted on: it describes the estimation data much "
                   "better than other data (overfit?)")
    elif sel.get("folds") and sel.get("held_out_mse") is None:
        out.append(f"its {sel['what']} simulation diverges on a held-out block of the data")
    return out


def select_for_simulation(
    problem: Problem, candidates: np.ndarray, criterion: Criterion, *,
    metadata: dict | None = None, max_passes: int = 10,
    progress: ProgressFn | None = None, started: float | None = None,
) -> NarxModel:
    """The structure and coefficients that simulate best, by an information criterion.

    Each candidate structure (rows of ``candidates``, masks over the whole term
    space, e.g. the GA's best by the one-step criterion) is fitted by least
    squares, refined on its free-run error
    (:func:`~spm_sysid.core.narx.refine.refine_simulation`) and scored by
    ``criterion`` with the free-run SSE in place of the one-step SSE (so AIC
    becomes ``N ln(SSE_sim / N) + 2k``). From the best, a local search
    (:func:`~spm_sysid.core.narx.search.local_search`) removes or adds one term
    at a time (terms of the candidates; every usable term in spaces of at most
    100) while that lowers the simulation criterion. Structures whose
    simulation diverges on the estimation data are never returned.

    Raises
    ------
    DataError
        When every candidate's simulation diverges on the estimation data.
    """
    ts = problem.term_space
    u, y, segments = problem.u, problem.y, problem.segments
    rows = problem.rows
    started = time.perf_counter() if started is None else started
    report = progress or (lambda p: None)
    scored: dict[bytes, tuple[float, NarxModel | None]] = {}
    refinements = 0
    current: list[NarxModel | None] = [None]  # the search's current structure's model

    def score_one(mask: np.ndarray, start: NarxModel | None = None) -> float:
        nonlocal refinements
        key = np.packbits(mask).tobytes()
        if key in scored:
            return scored[key][0]
        value, model = np.inf, None
        if mask.any() and not (mask & ~problem.usable).any():
            try:
                fit = problem.fit(mask)
            except ValueError:  # linearly dependent on this data
                fit = None
            if fit is not None:
                model = problem.model(mask, fit)
                if start is not None:  # warm start: a neighbour's refined coefficients
                    theta = dict(zip(start.term_indices, start.coefficients))
                    ls = model.coefficients
                    model.coefficients = np.array([theta.get(i, 0.0)
                                                   for i in model.term_indices])
                    ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
                    if not ref.success:
                        model.coefficients = ls
                        ref = refine_simulation(model, u, y, segments)
                else:
                    ref = refine_simulation(model, u, y, segments)
                refinements += 1
                if ref.success and np.isfinite(ref.sse):
                    model.coefficients = ref.coefficients
                    value = _simulation_value(criterion, ref.sse, rows, mask, ref.coefficients,
                                              problem)
                    model.metadata = {"refinement": ref.message, "free_run_sse": ref.sse,
                                      "least_squares_free_run_sse": ref.sse_start}
                else:
                    model = None
        scored[key] = (value, model)
        best = min(v for v, _ in scored.values())
        report(Progress("refinement", refinements, 0, best, elapsed=time.perf_counter() - started))
        return value

    for mask in candidates:
        score_one(mask)
    if not scored or min(v for v, _ in scored.values()) == np.inf:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    best_key = min(scored, key=lambda k: scored[k][0])
    start = np.unpackbits(np.frombuffer(best_key, dtype=np.uint8))[:ts.n_terms].astype(bool)
    pool = problem.usable.copy() if ts.n_terms <= 100 else candidates.any(axis=0)
    current[0] = scored[best_key][1]

    def score(masks: np.ndarray) -> np.ndarray:
        return np.array([score_one(m, current[0]) for m in masks])

    def moved(mask: np.ndarray, value: float) -> None:
        current[0] = scored[np.packbits(mask).tobytes()][1]

    found = local_search(score, start, pool, moves=("remove", "add"),
                         start_value=scored[best_key][0], max_steps=max_passes, on_step=moved)
    best = found.mask
    value, model = scored[np.packbits(best).tobytes()]
    # the search's moves ran a few Levenberg-Marquardt steps each: finish the winner's
    final = refine_simulation(model, u, y, segments)
    refinements += 1
    if final.success and final.sse < model.metadata["free_run_sse"]:
        model.coefficients = final.coefficients
        value = _simulation_value(criterion, final.sse, rows, best, final.coefficients,
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


def _simulation_value(criterion: Criterion, sse: float, rows: int, mask: np.ndarray,
                      coefficients: np.ndarray, problem: Problem) -> float:
    """The criterion with the free-run SSE (standardised coefficients as for one-step)."""
    beta = np.zeros((1, problem.term_space.n_terms))
    y_norm = float(np.linalg.norm(problem.target)) * problem.y_scale or 1.0
    beta[0, mask] = coefficients * problem.column_norms[mask] / y_norm
    v = float(criterion(np.array([max(sse, 1e-300)]), rows, np.array([mask.sum()]), beta)[0])
    return v if np.isfinite(v) else np.inf


def _certify_search(problem: Problem, evaluator, result: GAResult, crit: Criterion,
                    time_limit: float, report: ProgressFn, started: float) -> dict:
    """Certify the GA's result in place (a better structure found replaces it)."""
    from .certify import certify

    def on_nodes(nodes: int, best: float, lower: float) -> None:
        report(Progress("certification", nodes, 0, best, bound=lower,
                        elapsed=time.perf_counter() - started))

    try:
        cert = certify(None, None, crit, warm_start=result.best_mask, time_limit=time_limit,
                       evaluator=evaluator, progress=on_nodes)
    except ValueError as exc:  # a criterion that cannot be certified
        return {"status": "refused", "reason": str(exc)}
    names = problem.term_space.term_names()
    cert.terms = [names[i] for i in np.flatnonzero(problem.expand(cert.mask))]
    doc = cert.to_dict()
    doc["ga_value"] = float(result.best_score)
    if cert.value < result.best_score:
        result.best_mask, result.best_score = cert.mask.copy(), cert.value
    return doc

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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from ..progress import Progress, ProgressFn
from .criteria import Criterion, get_criterion
from .ga import GAConfig, GAResult, GenerationStats, run_ga
from .model import NarxModel
from .problem import Problem, check_samples, validate_signals
from .refine import refine_simulation
from .search import local_search
from .terms import TermSpace

__all__ = ["FOCUS", "IdentificationResult", "check_samples", "identify", "identify_problem",
           "select_for_simulation", "validate_signals"]

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
                            certify_time_limit=certify_time_limit, progress=progress)


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
    progress: ProgressFn | None = None,
    started: float | None = None,
) -> IdentificationResult:
    """:func:`identify` on a problem already built (see there for the parameters).

    ``started`` is ``time.perf_counter()`` at the job's start (progress reports
    count their seconds from it; default: now).
    """
    crit = get_criterion(criterion)
    if focus not in FOCUS:
        raise ValueError(f"focus must be one of {', '.join(FOCUS)}, got {focus!r}")
    started = time.perf_counter() if started is None else started
    report = progress or (lambda p: None)
    ga = ga or GAConfig()
    evaluator = problem.evaluator(crit)

    def on_generation(stats: GenerationStats):
        report(Progress("search", stats.generation, ga.generations, stats.best,
                        stats.evaluations, elapsed=time.perf_counter() - started))
        return None if callback is None else callback(stats)

    result = run_ga(evaluator, ga, seed=seed, callback=on_generation)
    if not np.isfinite(result.best_score):
        raise DataError(
            "no structure could be fitted: every structure the search tried has linearly "
            "dependent regressors on this data (repeated or constant signals?)"
        )
    certificate = None
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
        **({"excluded_zero_terms": excluded["zero"]} if excluded["zero"] else {}),
        **({"excluded_duplicate_terms": excluded["duplicate"]} if excluded["duplicate"]
           else {}),
        **({"certificate": certificate} if certificate is not None else {}),
    }
    if focus == "simulation":
        candidates = problem.expand(evaluator.ranked(shortlist))
        model = select_for_simulation(problem, candidates, crit, metadata=info,
                                      progress=report, started=started)
    else:
        model = problem.model(result.best_mask, criterion=crit.name,
                              criterion_value=result.best_score, metadata=info)
    return IdentificationResult(model=model, ga=result, problem=problem)


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

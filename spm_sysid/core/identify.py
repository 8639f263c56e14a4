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

from .blas import one_blas_thread
from .defaults import AUTO_CERTIFY_TERMS, MAX_JUDGED_TERMS, OVERFIT_RATIO, ROWS_PER_TERM
from .errors import DataError
from .fit.criteria import Criterion, get_criterion
from .fit.lstsq import sse_floor
from .fit.problem import Problem, check_samples, validate_signals
from .model.narx import NarxModel
from .model.terms import TermSpace
from .progress import Progress, ProgressFn
from .search.ga import GAConfig, GAResult, GenerationStats, run_ga
from .search.local import polish
from .select.simulation import select_for_simulation, validated_simulation
from .select.validated import (
    FOLDS,
    SIMULATION_FOLDS,
    SIMULATION_REPEATS,
    candidate_structures,
    cv_scores,
    informative_folds,
)
from .settings import SETTINGS, check
from .validate.open_loop import HORIZON, open_loop_check

__all__ = ["FOCUS", "SELECTION", "IdentificationResult", "check_samples", "identify",
           "identify_problem", "select_for_simulation", "validate_signals"]

#: What a model is selected and fitted for (the schema's choices of ``focus``).
FOCUS = SETTINGS["focus"].choices



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
        search (see :func:`spm_sysid.core.search.ga.run_ga`).
    segments : list of (start, stop), optional
        Contiguous parts of the record (``[start, stop)`` indices, e.g. from
        :func:`spm_sysid.core.model.segments.find_segments`): regression rows are built
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
        space by branch and bound (:mod:`spm_sysid.core.search.certify`; AIC and
        BIC), within this many seconds; the result is in
        ``model.metadata["certificate"]`` (``optimal``, or ``limit`` with the
        lower bound and gap, or ``refused`` with the reason). A better structure
        found on the way replaces the GA's.
    selection : {"auto", "criterion", "validated"}
        How the structure is chosen: by the criterion on the estimation data
        (the paper's), or by its error on held-out blocks of the estimation
        data (:mod:`spm_sysid.core.select.validated`; the final model is fitted
        on all of it). ``auto``: validated for the simulation focus, and for the
        prediction focus when there are fewer than 10 rows per candidate term.
    max_terms : int
        Structures of more terms are not selected (0: no limit).
    polish : bool
        After the GA, :func:`~spm_sysid.core.search.local.polish`: a local search
        from its best structure (one term added, removed or swapped while that
        improves the criterion), then kicks (4 to 11 terms flipped, a cheap
        add/remove descent, and the full search from the promising ones), within
        a budget of structures scored (not seconds), so the result does not
        depend on the machine's speed. ``model.metadata["polish"]`` says what it
        changed.
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
    # the Python API is an edge: its settings are checked here, by the schema, once
    focus, selection = check("focus", focus), check("selection", selection)
    problem = Problem.from_signals(u, y, term_space, segments)
    return identify_problem(problem, criterion=criterion, ga=ga, seed=seed, callback=callback,
                            focus=focus, shortlist=shortlist,
                            certify_time_limit=certify_time_limit, selection=selection,
                            max_terms=max_terms, polish=polish,
                            auto_certify_time_limit=auto_certify_time_limit, progress=progress)


#: How a structure is chosen (see :mod:`spm_sysid.core.select.validated`).
SELECTION = SETTINGS["selection"].choices

#: ``auto`` validates the prediction focus too when there are fewer rows than this many
#: per usable candidate term (where an in-sample criterion can overfit badly).
AUTO_ROWS_PER_TERM = ROWS_PER_TERM


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
    horizon: int = 0,
    simulation_folds: int = SIMULATION_FOLDS,
    simulation_repeats: int = SIMULATION_REPEATS,
    progress: ProgressFn | None = None,
    started: float | None = None,
) -> IdentificationResult:
    """:func:`identify` on a problem already built (see there for the parameters).

    Its settings are taken as checked (at the edge: :func:`identify`, a job's
    :class:`~spm_sysid.core.jobs.settings.JobSettings`, a study's configuration).
    ``started`` is ``time.perf_counter()`` at the job's start (progress reports
    count their seconds from it; default: now). ``check_data``: run the data
    check (:mod:`spm_sysid.core.validate.excitation`) first; its warnings go into
    ``model.metadata["warnings"]``. ``horizon``: the k of the k-step prediction that
    integrating or open-loop unstable records are judged on with the simulation focus
    (0: :data:`~spm_sysid.core.validate.open_loop.HORIZON`). ``simulation_folds``,
    ``simulation_repeats``: held-out blocks of the simulation focus and how many times
    they are laid (:data:`~spm_sysid.core.select.validated.SIMULATION_FOLDS`; the accuracy
    benchmark measures the linear/nonlinear call with other schemes).
    """
    crit = get_criterion(criterion)  # the name (checked at the edge) to its object, once
    started = time.perf_counter() if started is None else started
    report = progress or (lambda p: None)
    ga = ga or GAConfig()
    warnings: list[str] = []
    data_check = None
    if check_data:
        from .validate.excitation import check_problem

        data_check = check_problem(problem, criterion=crit.name)
        warnings += data_check.warnings
    evaluator = problem.evaluator(crit, max_terms=max_terms)

    def on_generation(stats: GenerationStats):
        report(Progress("search", stats.generation, ga.generations, stats.best,
                        stats.evaluations, elapsed=time.perf_counter() - started))
        return None if callback is None else callback(stats)

    result = run_ga(evaluator, ga, seed=seed, callback=on_generation)
    if not np.isfinite(result.best_score):
        from .validate.excitation import describe_glitches, glitches

        glitch = describe_glitches(problem.y, glitches(problem.y, problem.segments),
                                   problem.term_space.output)
        raise DataError(
            "no structure could be fitted: every structure the search tried has linearly "
            "dependent regressors on this data ("
            + (glitch if glitch else "repeated or constant signals?") + ")"
            + (f", or more than max_terms = {max_terms} terms" if max_terms else "")
        )
    polished = _polish(problem, evaluator, result) if polish else None
    mode, note = _selection_mode(selection, focus, problem)
    open_loop = None
    if focus == "simulation":
        open_loop = open_loop_check(problem.u, problem.y, problem.segments,
                                    min(max(problem.term_space.ny, 2), 10))
    k_step = None
    if open_loop is not None and not open_loop.free_run_applies:
        k_step = horizon or HORIZON
        warnings.append(open_loop.reason().replace("judged on the k-step prediction",
                                                   f"judged on the {k_step}-step prediction"))
    folds, fold_note = (informative_folds(problem, simulation_folds, simulation_repeats)
                        if focus == "simulation" else informative_folds(problem, FOLDS))
    if mode == "validated" and not folds:
        mode, note = "criterion", fold_note
        if selection != "criterion" and "excitation" in fold_note:
            warnings.append(f"judged by the criterion on all the data, not on held-out "
                            f"blocks: {fold_note}")
    elif fold_note:
        note = f"{note}; {fold_note}"
    certificate = None
    if certify_time_limit is None and auto_certify_time_limit > 0:
        from .search.certify import CERTIFIABLE

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
        **({"open_loop": {**open_loop.to_dict(), **({"horizon": k_step} if k_step else {})}}
           if open_loop is not None else {}),
    }
    simulate = focus == "simulation" and k_step is None
    chosen = None
    if mode == "validated":
        model, chosen = _select_validated(problem, evaluator, folds, crit, shortlist,
                                          max_terms, simulate, report, started, k_step)
        model.metadata = {**info, **model.metadata}
    elif simulate:
        candidates = problem.expand(evaluator.ranked(shortlist))
        model = select_for_simulation(problem, candidates, crit, metadata=info,
                                      progress=report, started=started)
    else:
        model = problem.model(result.best_mask, criterion=crit.name,
                              criterion_value=result.best_score, metadata=info)
    model.metadata["selection"] = _generalisation(problem, folds, model, mode, note, simulate,
                                                  chosen, k_step)
    warnings += _overfit_warnings(problem, model)
    if warnings:
        model.metadata["warnings"] = warnings
    return IdentificationResult(model=model, ga=result, problem=problem)


def _polish(problem: Problem, evaluator, result: GAResult) -> dict:
    """The polish (:func:`~spm_sysid.core.search.local.polish`) of the GA's best, in place.

    What it did, for the document.
    """
    ga_value = float(result.best_score)
    if not np.isfinite(ga_value):
        return {"ga_value": None, "value": None, "steps": 0, "structures": 0}
    usable = np.flatnonzero(problem.usable) if len(problem.usable) == evaluator.n_terms \
        else np.arange(evaluator.n_terms)
    res = polish(evaluator.score, result.best_mask, np.ones(evaluator.n_terms, dtype=bool),
                 value=ga_value, kick_terms=usable, usable_terms=int(problem.usable.sum()))
    if res.value < ga_value:
        result.best_mask, result.best_score = res.mask.copy(), res.value
    return {"ga_value": ga_value, "value": float(result.best_score), "steps": res.steps,
            "structures": res.scored, "kicks": res.kicks, "moves": list(res.moves),
            "stopped": res.stopped, "budget": res.budget}


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




def _select_validated(problem, evaluator, folds, crit, shortlist, max_terms, simulate,
                      report, started, k_step=None) -> tuple[NarxModel, dict]:
    """Validated selection (see :mod:`spm_sysid.core.select.validated`); model and record.

    ``k_step``: judge on the held-out k-step prediction (an integrating record).
    """
    from .search.forward import forward_selection_path

    limit = min(MAX_JUDGED_TERMS, max(1, problem.rows // ROWS_PER_TERM))
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
        return validated_simulation(problem, candidates, folds, crit, max_terms, report,
                                    started)
    scores = cv_scores(problem, folds, candidates, simulate=k_step is not None,
                       horizon=k_step)
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


def _generalisation(problem, folds, model, mode, note, simulate, chosen, k_step=None) -> dict:
    """How the structure was chosen and how it does on held-out data (the document's)."""
    what = f"{k_step}-step" if k_step else "free-run" if simulate else "one-step"
    out = {"method": mode, "note": note, "what": what, "folds": len(folds)}
    if chosen is None and folds:
        sc = cv_scores(problem, folds, [model.mask], simulate or bool(k_step), horizon=k_step)
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
    # errors at rounding level (an exact fit) have no meaningful ratio: the floor counts
    floor = sse_floor(float(np.linalg.norm(problem.target)) * problem.y_scale) / problem.rows
    out["ratio"] = (max(held, floor) / max(in_sample, floor)
                    if held is not None and in_sample is not None else None)
    return out


def _overfit_warnings(problem, model) -> list[str]:
    """Warnings when the model may fit noise: its size, its held-out error."""
    out = []
    k, rows = len(model.term_indices), problem.rows
    if k > rows / ROWS_PER_TERM:
        out.append(f"{k} terms from {rows} rows (more than one term per {ROWS_PER_TERM} "
                   "rows): the model may fit noise; prefer BIC or AICc, max_terms, fewer "
                   "lags, or selection: validated")
    sel = model.metadata.get("selection") or {}
    ratio = sel.get("ratio")
    if ratio is not None and ratio > OVERFIT_RATIO:
        out.append(f"its {sel['what']} error on held-out blocks is {ratio:.1f} times its error "
                   "on the data it was fitted on: it describes the estimation data much "
                   "better than other data (overfit?)")
    elif sel.get("folds") and sel.get("held_out_mse") is None:
        out.append(f"its {sel['what']} simulation diverges on a held-out block of the data")
    return out


def _certify_search(problem: Problem, evaluator, result: GAResult, crit: Criterion,
                    time_limit: float, report: ProgressFn, started: float) -> dict:
    """Certify the GA's result in place (a better structure found replaces it)."""
    from .search.certify import certify

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

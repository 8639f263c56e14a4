"""Choosing the structure as the plan says, and the account of the choice.

One selector per plan (:class:`~spm_sysid.core.select.plan.SelectionPlan`), each
small; :func:`choose` dispatches once:

* **criterion, one-step** (the paper's): the search's best, least squares;
* **criterion, free-run**: :func:`~.simulation.select_for_simulation`;
* **validated, free-run**: :func:`~.finalists.validated_simulation`;
* **validated, one-step or k-step**: :func:`validated_prediction` -- the
  candidates' held-out errors by least squares on each fold, the fewest terms
  within one standard error of the best.

:func:`selection_account` is what the document's ``metadata.selection`` says;
:func:`overfit_warnings` what the answer warns about the model's size and its
held-out error.
"""

from __future__ import annotations

import time

import numpy as np

from ..defaults import (
    LONG_CANDIDATES,
    MAX_CANDIDATES,
    MAX_JUDGED_TERMS,
    OVERFIT_RATIO,
    ROWS_PER_TERM,
)
from ..errors import DataError
from ..model.narx import NarxModel
from ..progress import Progress
from .finalists import validated_simulation
from .folds import is_long
from .plan import SelectionPlan
from .scores import candidate_structures, cv_scores, held_out_floor
from .simulation import select_for_simulation

__all__ = ["choose", "overfit_warnings", "selection_account", "validated_prediction"]


def choose(plan: SelectionPlan, problem, evaluator, best_mask, best_score, crit, options,
           info: dict, report, started) -> tuple[NarxModel, dict | None]:
    """The model the plan chooses, with ``info`` in its metadata; the validated account."""
    if plan.mode == "validated":
        candidates = _candidates(problem, evaluator, options)
        if plan.simulate:
            model, chosen = validated_simulation(
                problem, candidates, plan.folds, crit, options.max_terms, report, started,
                plan.open_loop is not None and plan.open_loop.kind == "integrating")
        else:
            model, chosen = validated_prediction(problem, evaluator, candidates, plan, crit,
                                                 report, started)
        model.metadata = {**info, **model.metadata}
        return model, chosen
    if plan.simulate:
        candidates = problem.expand(evaluator.ranked(options.shortlist))
        return select_for_simulation(problem, candidates, crit, metadata=info,
                                     progress=report, started=started), None
    return problem.model(best_mask, criterion=crit.name, criterion_value=best_score,
                         metadata=info), None


def _candidates(problem, evaluator, options) -> np.ndarray:
    """The structures validated selection judges (the short-list, sizes, forward paths)."""
    from ..search.forward import forward_selection_path

    limit = min(MAX_JUDGED_TERMS, max(1, problem.rows // ROWS_PER_TERM))
    degree = problem.term_space.term_degrees[problem.usable]

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

    candidates = candidate_structures(problem, evaluator, options.shortlist, forward=forward,
                                      max_candidates=LONG_CANDIDATES if is_long(problem)
                                      else MAX_CANDIDATES)
    # structures of more than one term per ROWS_PER_TERM rows are not judged: the
    # warning threshold of an overfit (and max_terms, when smaller)
    cap = min(limit, options.max_terms) if options.max_terms else limit
    candidates = candidates[candidates.sum(axis=1) <= cap]
    if not len(candidates):
        raise DataError(f"no candidate structure of at most {cap} terms could be fitted")
    return candidates


def validated_prediction(problem, evaluator, candidates, plan: SelectionPlan, crit, report,
                         started) -> tuple[NarxModel, dict]:
    """One-step (or k-step) held-out errors; the fewest terms within one SE of the best."""
    k_step = plan.judged == "k-step"
    scores = cv_scores(problem, plan.folds, candidates, simulate=k_step,
                       horizon=plan.horizon)
    report(Progress("held-out blocks", len(candidates), len(candidates),
                    elapsed=time.perf_counter() - started))
    i = scores.best()
    if i is None:
        raise DataError("no candidate structure could be fitted on the held-out folds")
    mask = scores.masks[i]
    model = problem.model(mask, criterion=crit.name,
                          criterion_value=evaluator.cached_score(problem.restrict(mask)))
    return model, {"held_out_mse": scores.mean[i], "held_out_stderr": scores.stderr[i],
                   "candidates": len(candidates)}


def selection_account(problem, plan: SelectionPlan, model, chosen: dict | None) -> dict:
    """How the structure was chosen and how it does on held-out data (the document's)."""
    out = {"method": plan.mode, "note": plan.note, "what": plan.judged if plan.judged !=
           "k-step" else f"{plan.horizon}-step", "folds": len(plan.folds)}
    if chosen is None and plan.folds:
        sc = cv_scores(problem, plan.folds, [model.mask], plan.judged != "one-step",
                       horizon=plan.horizon)
        chosen = {"held_out_mse": sc.mean[0], "held_out_stderr": sc.stderr[0]}
    if chosen:
        out.update({k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                    for k, v in chosen.items()})
    if plan.simulate:
        sse = (model.metadata.get("simulation") or {}).get("free_run_sse")
        in_sample = None if sse is None else sse / problem.rows
    else:
        in_sample = model.mse
    out["in_sample_mse"] = in_sample
    held = out.get("held_out_mse")
    # errors at rounding level (an exact fit) have no meaningful ratio: the floor counts
    floor = held_out_floor(problem)
    out["ratio"] = (max(held, floor) / max(in_sample, floor)
                    if held is not None and in_sample is not None else None)
    return out


def overfit_warnings(problem, model) -> list[str]:
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
                   "better than other data (overfit?)" + _against_linear(sel))
    elif sel.get("folds") and sel.get("held_out_mse") is None:
        out.append(f"its {sel['what']} simulation diverges on a held-out block of the data")
    return out


def _against_linear(selection: dict) -> str:
    """What the held-out blocks said of a nonlinear model against the best linear one.

    A model may fit its own data far better than other data and still simulate
    the other data far better than any linear model (the robot arm's
    ``--focus simulation --orders auto``: 7.2x its own error, 0.018x the best
    linear's): the warning says both. Only when the model returned is the one the
    paired test judged, unchanged (not shrunk by the guard, not a fallback).
    """
    call = selection.get("linear_or_nonlinear") or {}
    ratio = call.get("ratio")
    if (call.get("challenger_fate") != "returned" or call.get("choice") != "nonlinear"
            or ratio is None or not np.isfinite(ratio)):
        return ""
    p = call.get("p_value")
    return (f"; on those blocks it is still {ratio:.2g}x the best linear model's error"
            + (f" (p = {p:.2g})" if p is not None else ""))

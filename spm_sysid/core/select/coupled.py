"""Several outputs: the coupled model judged by its coupled free run, in both focuses.

Each output's own selection simulates that output with the other outputs
*measured*. Put together, every output's simulated value feeds every other's
terms, and a model whose outputs are each fine alone can diverge coupled. So
the joined model competes here, as one of the finalists, on the **coupled**
free run:

* **finalists** -- the outputs' own choices put together, as they are and
  jointly refined on the coupled free-run error
  (:func:`~spm_sysid.core.fit.refine_coupled.refine_coupled`); and the linear MIMO
  ARX structure of every order in the space (each output's constant, own lags,
  the inputs' and the other outputs' lags up to that order), by least squares
  and jointly refined;
* **held-out blocks** (:data:`COUPLED_FOLDS`) -- each finalist's structures are
  fitted on the rest of the estimation data (least squares; the jointly refined
  one also refined there, on :func:`~spm_sysid.core.select.folds.refinement_windows`
  of it when the record is long, as a single output's folds are) and simulated
  coupled over the block from its first samples; the error is the sum over
  outputs of the MSE divided by the output's variance; a run that leaves an
  output's range rejects the finalist;
* **choice** -- the one linear/nonlinear call of single-output selection
  (:func:`~spm_sysid.core.select.call.linear_or_nonlinear`): the best linear
  finalist, unless a nonlinear one simulates the blocks better by more than the
  noise of that comparison;
* **guard** -- the chosen model, fitted on all data, must stay in range coupled,
  driven by every segment's input, shifted, reversed and with random phases
  (:func:`coupled_stress_check`); otherwise the next finalist.

A model whose coupled free run diverges is never returned while another
finalist does not; when every one diverges, the joined model is returned and
the answer says so first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..defaults import (
    COUPLED_FOLDS,
    JOINT_FOLD_STEPS,
    SIGNIFICANCE,
    STRESS_FACTOR,
)
from ..files import json_float
from ..fit.criteria import get_criterion, standardised_value
from ..fit.refine_coupled import refine_coupled
from ..model.coupled import CoupledCompiled, coupled_run
from ..model.mimo import MimoModel, augmented_inputs
from ..model.narx import NarxModel
from ..model.segments import rows_segments
from .call import linear_or_nonlinear
from .coupled_fits import fit_least_squares, least_squares_fits, one_pass, row_factor
from .folds import block_splits, final_samples, refinement_windows, windowed_rows
from .guard import stress_inputs
from .scores import mean_and_stderr
from .simulation import linear_masks

__all__ = ["COUPLED_ESTIMATORS", "COUPLED_FOLDS", "JOINT_FOLD_STEPS", "coupled_folds",
           "coupled_stress_check", "fit_least_squares", "linear_mimo", "select_coupled"]

#: How a linear finalist's coefficients are estimated: least squares (the equation
#: error), or from there refined jointly on the coupled free-run error.
COUPLED_ESTIMATORS = ("least squares", "jointly refined")


def coupled_folds(segments: list[tuple[int, int]], n: int, lag: int, k: int = COUPLED_FOLDS
                  ) -> list[tuple[list[tuple[int, int]], list[tuple[int, int]]]]:
    """K contiguous blocks over the segments: (held-out ranges, training segments) each.

    Fewer when the blocks would be too short; empty when not even two fit.
    """
    while k >= 2:
        splits = block_splits(segments, k, 1, lag)
        if splits and all(rest for _, rest in splits):
            return [(rows_segments(held, n, lag), rows_segments(rest, n, 0))
                    for held, rest in splits]
        k -= 1
    return []


def linear_mimo(model: MimoModel, order: int) -> MimoModel:
    """The linear MIMO ARX structure of ``order`` in each output's space (zero coefficients).

    When the outputs' spaces differ (``orders: auto`` gives each output its own
    proposal), each output's linear terms come from a linear space of the largest
    order of them all, so that every output reaches ``order``.
    """
    spaces = [m.term_space for m in model.models]
    top = max(s.order for s in spaces)
    own = {(s.ny, tuple(s.nus), s.degree) for s in spaces}
    models = []
    for space in spaces:
        if len(own) > 1:
            space = replace(space, ny=top, nu=(top,) * len(space.nus), degree=1)
        masks = linear_masks(space)
        mask = masks[min(order, len(masks)) - 1]
        idx = [int(i) for i in np.flatnonzero(mask)]
        models.append(NarxModel(space, idx, np.zeros(len(idx))))
    return MimoModel(model.outputs, model.inputs, models, {})


def _scales(Y: np.ndarray, segments) -> np.ndarray:
    rows = np.concatenate([Y[a:b] for a, b in segments])
    v = rows.var(axis=0)
    return np.where(v > 0, v, 1.0)


def _held_out_error(model: MimoModel, u, Y, held, scale) -> float:
    """Sum over outputs of the coupled free run's MSE / variance on the held-out ranges."""
    cc = CoupledCompiled.from_models(model.models, u.shape[1])
    thetas = [m.coefficients for m in model.models]
    sse, rows = np.zeros(Y.shape[1]), 0
    for a, b in held:
        if b - a <= cc.max_lag:
            continue
        sim, div = coupled_run(cc, thetas, u[a:b], Y[a:b])
        if any(d is not None for d in div) or not np.all(np.isfinite(sim)):
            return np.inf
        e = Y[a + cc.max_lag:b] - sim
        sse += np.sum(e * e, axis=0)
        rows += len(e)
    return float(np.sum(sse / max(rows, 1) / scale)) if rows else np.nan


def coupled_stress_check(model: MimoModel, u: np.ndarray, Y: np.ndarray,
                         segments: list[tuple[int, int]]) -> str | None:
    """Why the coupled model does not stay in range off the estimation data, or None.

    Its coupled free run on every segment, and driven by each segment's input
    shifted by half its length, reversed in time, and with random phases
    (:data:`~spm_sysid.core.select.validated.SURROGATES` draws), from the segment's
    own initial outputs, must keep every output inside its measured range widened
    by :data:`~spm_sysid.core.select.validated.STRESS_FACTOR` spans.
    """
    cc = CoupledCompiled.from_models(model.models, u.shape[1])
    thetas = [m.coefficients for m in model.models]
    lo, hi = Y.min(axis=0), Y.max(axis=0)
    span = np.maximum(hi - lo, 1e-300)
    bounds = [(float(a - STRESS_FACTOR * s), float(b + STRESS_FACTOR * s))
              for a, b, s in zip(lo, hi, span)]
    for a, b in segments:
        if b - a <= cc.max_lag:
            continue
        for label, uu in stress_inputs(u[a:b]):
            sim, div = coupled_run(cc, thetas, uu, Y[a:b], bounds)
            bad = [model.outputs[i] for i, d in enumerate(div) if d is not None]
            if bad or not np.all(np.isfinite(sim)):
                names = ", ".join(bad) or "an output"
                return f"its coupled simulation driven by {label} left the range of {names}"
    return None


def _fold_errors(model: MimoModel, how: str, folds, u, Y, scale) -> list[float]:
    """The finalist's coupled held-out error on each fold (NaN: not fitted there)."""
    row = []
    fits = least_squares_fits(model, u, Y, [train for _, train in folds])
    for (held, train), fitted in zip(folds, fits):
        if fitted is None:
            row.append(np.nan)
            continue
        if how == "jointly refined":  # on windows of a long record (the cost of a short one)
            fitted, _ = refine_coupled(fitted, u, Y, refinement_windows(train, model.max_lag),
                                       max_evaluations=JOINT_FOLD_STEPS)
        row.append(_held_out_error(fitted, u, Y, held, scale))
    return row


def _terms(model: MimoModel) -> int:
    return sum(len(m.term_indices) for m in model.models)


def _degree(model: MimoModel) -> int:
    return max(max((int(m.term_space.term_degrees[i]) for i in m.term_indices), default=0)
               for m in model.models)


def select_coupled(joined: MimoModel, u: np.ndarray, Y: np.ndarray,
                   segments: list[tuple[int, int]],
                   progress: Callable[[int, int], None] | None = None
                   ) -> tuple[MimoModel, dict]:
    """The finalist to return, judged on the coupled free run (see the module doc).

    Parameters
    ----------
    joined : MimoModel
        The outputs' own choices, put together (their coefficients as the jobs gave).
    u, Y : ndarray
        Inputs (n, m) and outputs (n, q) of the record.
    segments : list of (start, stop)
        The estimation segments.
    progress : callable, optional
        ``progress(done, total)`` before and after each finalist's folds (total: the
        finalists and the final fit), so a long record's judgement says how far it is.

    Returns
    -------
    model : MimoModel
        The choice, fitted on all estimation data (refined jointly: :func:`_final_rows`).
    account : dict
        Finalists, their held-out errors, the linear/nonlinear call, the guard's
        removals, and ``all_diverge`` with the reason when every finalist diverged.
    """
    u = np.asarray(u, dtype=float)
    u = u[:, None] if u.ndim == 1 else u
    Y = np.asarray(Y, dtype=float)
    folds = coupled_folds(segments, len(Y), joined.max_lag)
    finalists = _coupled_finalists(joined)
    values = _judged(finalists, folds, u, Y, _scales(Y, segments), progress)
    means, stderr = zip(*(mean_and_stderr(r) for r in values)) if values else ((), ())
    account: dict = {"folds": len(folds), "significance": SIGNIFICANCE,
                     "finalists": [{"name": n, "fitted": h, "held_out_error": json_float(m),
                                    "held_out_stderr": json_float(s)}
                                   for (n, h, _), m, s in zip(finalists, means, stderr)]}
    call = linear_or_nonlinear(means, stderr, [_terms(f[2]) for f in finalists],
                               [_degree(f[2]) <= 1 for f in finalists], values)
    if call.linear is not None:
        if call.challenger is not None:
            account.update(nonlinear=finalists[call.challenger][0], ratio=call.ratio,
                           p_value=call.p_value)
        account["choice"] = call.choice
    return _first_that_holds(call.order, finalists, joined, u, Y, segments, means, stderr,
                             account)


def _first_that_holds(order, finalists, joined: MimoModel, u, Y, segments, means, stderr,
                      account: dict) -> tuple[MimoModel, dict]:
    """The first finalist in ``order`` fitted on all data that the guard keeps; the account."""
    removed = []
    for i in order:
        name, how, model = finalists[i]
        full = _fit_full(model, how, joined, u, Y, segments)
        if full is None:
            continue
        reason = coupled_stress_check(full, u, Y, segments)
        if reason:
            removed.append(f"{name} ({how}): {reason}")
            continue
        account.update(chosen=name, fitted=how, held_out_error=json_float(means[i]),
                       held_out_stderr=json_float(stderr[i]))
        if removed:
            account["removed_by_guard"] = removed
        return full, account
    why = ("every finalist's coupled free run left an output's range on held-out blocks "
           "or off the estimation data" + (f" ({removed[0]})" if removed else ""))
    account.update(chosen="the outputs' own choices", fitted="as chosen", all_diverge=why,
                   removed_by_guard=removed)
    return joined, account


def _judged(finalists, folds, u, Y, scale, progress) -> list[list[float]]:
    """Each finalist's held-out errors over the folds, ``progress(done, total)`` after each."""
    report = progress or (lambda done, total: None)
    values: list[list[float]] = []
    report(0, len(finalists) + 1)  # the final fit is the last step
    for _, how, model in finalists:
        values.append(_fold_errors(model, how, folds, u, Y, scale))
        report(len(values), len(finalists) + 1)
    return values


def _coupled_finalists(joined: MimoModel) -> list[tuple[str, str, MimoModel]]:
    """The outputs' own choices (as chosen, jointly refined) and the linear MIMO ARX.

    One linear model per order up to the largest lag of the choices, each fitted
    by every coupled estimator; a linear model equal to one before is left out.
    """
    top = max(m.term_space.order for m in joined.models)
    finalists: list[tuple[str, str, MimoModel]] = [("the outputs' own choices", "as chosen",
                                                    joined)]
    finalists.append(("the outputs' own choices", "jointly refined", joined))
    for k in range(1, top + 1):
        lin = linear_mimo(joined, k)
        if not any(_same(lin, f[2]) for f in finalists):
            finalists += [(f"linear MIMO ARX of order {k}", how, lin)
                          for how in COUPLED_ESTIMATORS]
    return finalists


def _fit_full(model: MimoModel, how: str, joined: MimoModel, u, Y, segments
              ) -> MimoModel | None:
    """The finalist fitted on all estimation data, each output's account filled in."""
    if how == "as chosen":
        return joined
    if how == "least squares":
        fitted = fit_least_squares(model, u, Y, segments)
        if fitted is None:
            return None
    else:
        start = joined if model is joined else fit_least_squares(model, u, Y, segments)
        if start is None:
            return None
        windows = _final_rows(start, segments)
        fitted, info = refine_coupled(start, u, Y, windows,
                                      rows=windowed_rows(windows, segments, start.max_lag))
        fitted.metadata["coupled_refinement"] = info
    models = [_accounted(m, t, augmented_inputs(u, Y, i), Y[:, i], segments,
                         uncertainty=how == "least squares")
              for i, (m, t) in enumerate(zip(fitted.models, joined.models))]
    return replace(fitted, models=models)


def _final_rows(model: MimoModel, segments: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The samples the final joint refinement fits on: every one while its Jacobian fits.

    The Jacobian holds rows x outputs x all outputs' terms numbers, and the
    refinement four such arrays; beyond
    :data:`~spm_sysid.core.defaults.JOINT_JACOBIAN_BYTES` it fits on windows spread
    over the record (:func:`~spm_sysid.core.select.folds.refinement_windows`) of as
    many rows as fit (two outputs of 3·10^5 samples, 56 terms: 269 MB a Jacobian,
    2.5 GB at the peak before).
    """
    return final_samples(segments, model.max_lag, 8 * len(model.models) * _terms(model))


def _accounted(m: NarxModel, template: NarxModel, u_aug, y, segments, uncertainty: bool
               ) -> NarxModel:
    """``m`` with the criterion, MSE, samples and metadata of the output's own choice.

    The criterion value is of the one-step SSE (standardised coefficients as the
    search scores them); with ``uncertainty``, least-squares standard errors.
    """
    from ..model.uncertainty import from_jacobian

    if template.criterion is None:
        raise ValueError(f"the model of {template.term_space.output} has no criterion")
    P, t_norm, sse, rows = _one_step_sums(m, u_aug, y, segments)
    norms = np.linalg.norm(P, axis=0)
    crit = get_criterion(template.criterion)
    beta = m.coefficients * norms / (t_norm or 1.0)
    value = standardised_value(crit, max(sse, 1e-300), rows, len(m.term_indices),
                               beta[None, :])
    meta = {k: v for k, v in template.metadata.items() if k not in ("simulation",)}
    return replace(m, criterion=crit.name, criterion_value=value, mse=sse / max(rows, 1),
                   n_samples=template.n_samples, metadata=meta,
                   uncertainty=from_jacobian(P, sse, rows) if uncertainty else m.uncertainty)


def _one_step_sums(m: NarxModel, u_aug, y, segments) -> tuple[np.ndarray, float, float, int]:
    """(P or its triangular factor, ||t||, the one-step SSE, the rows) of ``m`` on the segments.

    P and its factor have the same column norms and ``P^T P``; a long record gives
    the factor, a slice of rows at a time (:func:`.coupled_fits.row_factor`).
    """
    if one_pass(m, len(y)):
        P, t = m.term_space.regression(u_aug, y, segments, terms=m.term_indices)
        e = t - P @ m.coefficients
        return P, float(np.linalg.norm(t)), float(e @ e), len(t)
    r, rows = row_factor(m, u_aug, y, segments)
    k = len(m.term_indices)
    d = r[:k, k] - r[:k, :k] @ m.coefficients
    outside = float(r[k, k]) ** 2 if r.shape[0] > k else 0.0
    return r[:k, :k], float(np.linalg.norm(r[:, k])), float(d @ d) + outside, rows


def _same(a: MimoModel, b: MimoModel) -> bool:
    """The same structures (by the terms' names: the spaces may differ)."""
    return all(sorted(x.terms) == sorted(y.terms) for x, y in zip(a.models, b.models))



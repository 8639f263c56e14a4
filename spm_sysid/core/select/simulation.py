"""The simulation focus: structures judged by how they simulate, not by one-step error.

A structure is fitted by least squares, refined on its free-run error
(:func:`~spm_sysid.core.fit.refine.refine_simulation`) and scored by the
criterion with the free-run SSE in place of the one-step SSE
(:func:`simulation_value`). :class:`SimulationScorer` is that score, the one
scorer of both selections:

* :func:`select_for_simulation` (selection by the criterion): the candidates,
  then a local search around the best, the winner refined to convergence;
* validated selection (:mod:`spm_sysid.core.select.finalists`): the candidates
  screened in-sample with short refinements, finalists per degree and size
  judged on held-out blocks, the chosen one refined and checked by the
  stability guard.

:func:`linear_structures` are the full linear ARX structures of every order in
the space: what a user's one-line ``arx`` fit would give, a finalist always.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..defaults import POLISH_SPACE, SEARCH_STEPS
from ..errors import DataError
from ..fit.criteria import Criterion, standardised_value
from ..fit.evaluator import key_mask, mask_key
from ..fit.lstsq import sse_floor
from ..fit.problem import Problem
from ..fit.refine import free_run_uncertainty, refine_simulation
from ..model.narx import NarxModel
from ..model.uncertainty import Uncertainty
from ..progress import Progress, ProgressFn
from ..search.local import SearchResult, local_search
from .folds import final_samples, final_steps, refinement_windows, windowed_rows

__all__ = ["SimulationScorer", "linear_masks", "linear_orders", "linear_structures",
           "select_for_simulation", "simulation_value"]


def simulation_value(criterion: Criterion, sse: float, rows: int, mask: np.ndarray,
                     coefficients: np.ndarray, problem: Problem) -> float:
    """The criterion with the free-run SSE (standardised coefficients as for one-step).

    An SSE below rounding (:func:`~spm_sysid.core.fit.lstsq.sse_floor`) counts as the
    floor, as for one-step errors: exact fits score alike and the fewest terms win.
    """
    beta = np.zeros((1, problem.term_space.n_terms))
    y_norm = float(np.linalg.norm(problem.target)) * problem.y_scale or 1.0
    beta[0, mask] = coefficients * problem.column_norms[mask] / y_norm
    return standardised_value(criterion, max(sse, sse_floor(y_norm), 1e-300), rows,
                              int(mask.sum()), beta)


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
    segments : list of (start, stop), optional
        The samples refinements fit on (default: the problem's; a long record's
        :func:`~spm_sysid.core.select.folds.refinement_windows`): values of one
        scorer compare with each other.
    phase : str
        The progress phase its reports name (``refinement``, or ``screening``).

    Attributes
    ----------
    scored : dict
        Structure key (:func:`~spm_sysid.core.fit.evaluator.mask_key`) ->
        (value, refined model or None); +inf for one that cannot be fitted, whose
        simulation diverges on the estimation data, or without an input term (its
        free run ignores the input: it models no effect of it).
    """

    def __init__(self, problem: Problem, criterion: Criterion, *, steps: int | None = None,
                 max_terms: int = 0, notes: bool = False, progress: ProgressFn | None = None,
                 started: float | None = None, segments=None,
                 phase: str = "refinement") -> None:
        self.problem, self.criterion = problem, criterion
        self.segments = problem.segments if segments is None else segments
        self.phase = phase
        lag = problem.term_space.max_lag
        self.rows = sum(b - a - lag for a, b in self.segments)
        self.steps, self.max_terms, self.notes = steps, max_terms, notes
        self.report = progress or (lambda p: None)
        self.started = time.perf_counter() if started is None else started
        self.scored: dict[bytes, tuple[float, NarxModel | None]] = {}
        self.refinements = 0
        self.total = 0  # structures to refine, when known (progress)
        self.current: NarxModel | None = None  # the local search's current structure
        self.move_steps = SEARCH_STEPS  # evaluations of a warm-started move
        ts = problem.term_space  # the terms with an input in them: a structure needs one
        self.driven = np.array([any(ts.reads_input(i) for i in t) for t in ts.terms],
                               dtype=bool)

    def __call__(self, mask: np.ndarray) -> float:
        """The structure's value (scored once; warm-started from :attr:`current`)."""
        key = mask_key(mask)
        if key in self.scored:
            return self.scored[key][0]
        problem = self.problem
        value, model, ref = np.inf, None, None
        if (mask & self.driven).any() and not (mask & ~problem.usable).any() and not (
                self.max_terms and mask.sum() > self.max_terms):
            model, ref = self._refine(mask)
        if model is not None:
            self.refinements += 1
            if ref.success and np.isfinite(ref.sse):
                model.coefficients = ref.coefficients
                value = simulation_value(self.criterion, ref.sse, self.rows, mask,
                                         ref.coefficients, problem)
                if self.notes:
                    model.metadata = {"refinement": ref.message, "free_run_sse": ref.sse,
                                      "least_squares_free_run_sse": ref.sse_start}
            else:
                model = None
        self.scored[key] = (value, model)
        self.report(Progress(self.phase, self.refinements, self.total, self.best_value,
                             elapsed=time.perf_counter() - self.started))
        return value

    def _refine(self, mask: np.ndarray):
        """The structure refined: (model, refinement), or (None, None) when it cannot be fitted.

        A move of the local search starts from the current structure's refined
        coefficients (0 for a term it adds), without a least-squares fit on every
        row (on a long record that fit costs more than the refinement); least
        squares is the start when there is no current structure or that fails.
        """
        u, y, segments = self.problem.u, self.problem.y, self.segments
        start = self.current
        if start is not None:  # warm start: the neighbour's refined coefficients
            theta = dict(zip(start.term_indices, start.coefficients))
            indices = [int(i) for i in np.flatnonzero(mask)]
            model = NarxModel(term_space=start.term_space, term_indices=indices,
                              coefficients=np.array([theta.get(i, 0.0) for i in indices]),
                              n_samples=self.problem.n_samples)
            ref = refine_simulation(model, u, y, segments, max_evaluations=self.move_steps)
            if ref.success:
                return model, ref
        try:
            model = self.problem.model(mask)
        except ValueError:  # linearly dependent on this data
            return None, None
        steps = {} if self.steps is None else {"max_evaluations": self.steps}
        return model, refine_simulation(model, u, y, segments, **steps)

    @property
    def best_value(self) -> float:
        return min(v for v, _ in self.scored.values())

    def best_key(self) -> bytes:
        return min(self.scored, key=lambda k: self.scored[k][0])

    def search(self, candidates: np.ndarray, max_steps: int = 10) -> SearchResult | None:
        """Score the candidates, then remove or add one term at a time around the best.

        The terms a move may bring in: :meth:`move_pool`. None when no candidate simulates.
        """
        for mask in candidates:
            self(mask)
        best = self.best_key()
        if not np.isfinite(self.scored[best][0]):
            return None
        n = self.problem.term_space.n_terms
        return self.descend(key_mask(best, n), self.move_pool(candidates), max_steps)

    def move_pool(self, candidates: np.ndarray) -> np.ndarray:
        """The terms a move may bring in (bool over the term space).

        Every usable one in spaces of at most
        :data:`~spm_sysid.core.defaults.POLISH_SPACE` terms, else the candidates' terms.
        """
        if self.problem.term_space.n_terms <= POLISH_SPACE:
            return self.problem.usable.copy()
        return np.asarray(candidates, dtype=bool).any(axis=0)

    def descend(self, mask: np.ndarray, pool: np.ndarray, max_steps: int,
                evaluations: int = SEARCH_STEPS) -> SearchResult:
        """Remove or add one term of ``pool`` at a time from ``mask`` while the value falls.

        ``mask`` was scored; each move is warm-started from the current structure
        and refined by at most ``evaluations`` Levenberg-Marquardt evaluations.
        """
        self.current = self.scored[mask_key(mask)][1]
        self.move_steps = evaluations

        def moved(moved_to: np.ndarray, value: float) -> None:
            self.current = self.scored[mask_key(moved_to)][1]

        return local_search(lambda masks: np.array([self(m) for m in masks]),
                            mask, pool, moves=("remove", "add"),
                            start_value=self.scored[mask_key(mask)][0], max_steps=max_steps,
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
    :data:`~spm_sysid.core.defaults.POLISH_SPACE`) while that lowers the simulation
    criterion. Structures whose simulation diverges on the estimation data are never returned.

    Raises
    ------
    DataError
        When every candidate's simulation diverges on the estimation data.
    """
    u, y, segments = problem.u, problem.y, problem.segments
    windows = refinement_windows(segments, problem.term_space.max_lag)
    scorer = SimulationScorer(problem, criterion, notes=True, progress=progress,
                              started=started, segments=windows)
    found = scorer.search(candidates, max_steps=max_passes)
    if found is None:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    best = found.mask
    value, screened = scorer.scored[mask_key(best)]
    account = dict(screened.metadata)
    # the search's moves ran a few Levenberg-Marquardt steps each: finish the winner's
    final = refine_simulation(screened, u, y, segments, **final_steps(problem))
    coefficients = screened.coefficients
    if windows != list(segments):  # screened on windows: the winner's values on all rows
        account["free_run_sse"] = final.sse_start
        value = simulation_value(criterion, final.sse_start, problem.rows, best,
                                 coefficients, problem)
        account["screened_on_samples"] = scorer.rows
    if final.success and final.sse < account["free_run_sse"]:
        coefficients = final.coefficients
        value = simulation_value(criterion, final.sse, problem.rows, best, coefficients,
                                 problem)
        account["free_run_sse"] = final.sse
    model = replace(screened, coefficients=coefficients)  # the scorer's stays as scored
    one_step = model.residuals(u, y, segments)
    model.mse = float(one_step @ one_step) / len(one_step)
    model.criterion, model.criterion_value = criterion.name, value
    model.n_samples = problem.n_samples
    model.uncertainty, covariance = free_run_covariance(model, problem)
    model.metadata = {**(metadata or {}), "simulation": {
        **account, **covariance,
        "candidates": len(candidates), "refinements": scorer.refinements + 1,
        "local_search_steps": found.steps,
        "criterion_meaning": f"{criterion.name.upper()} of the free-run simulation error "
                             "(SSE of the simulated output) on the estimation data"}}
    return model


def free_run_covariance(model: NarxModel, problem: Problem
                        ) -> tuple[Uncertainty | None, dict]:
    """The returned model's free-run covariance (``free_run_uncertainty``) and its account.

    Its Jacobian on every estimation row while that fits
    :data:`~spm_sysid.core.defaults.FINAL_JACOBIAN_BYTES`, else on the windows a
    final refinement of a long record fits on
    (:func:`~spm_sysid.core.select.folds.final_samples`), scaled to all rows: a
    Jacobian of 10^6 rows and 60 terms (480 MB) beside the candidate matrix held a
    two-output job's peak.

    The account (for ``metadata.simulation``): ``no_uncertainty`` (why there is
    none) and, from windows, ``uncertainty_rows`` (the rows its Jacobian had).
    """
    segments = [(int(a), int(b)) for a, b in problem.segments]
    samples = final_samples(segments, problem.term_space.max_lag,
                            8 * len(model.term_indices), single=True)
    rows = windowed_rows(samples, segments, problem.term_space.max_lag)
    found, why = free_run_uncertainty(model, problem.u, problem.y, samples, rows=rows)
    lag = problem.term_space.max_lag
    return found, {**({"no_uncertainty": why} if why else {}),
                   **({"uncertainty_rows": sum(b - a - lag for a, b in samples)}
                      if rows is not None and found is not None else {})}


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
    return [mask for _, mask in linear_orders(term_space, usable)]


def linear_orders(term_space, usable: np.ndarray | None = None
                  ) -> list[tuple[int, np.ndarray]]:
    """Each distinct full linear ARX structure with its order k (see :func:`linear_masks`)."""
    ts = term_space
    lin = ts.linear
    index = {t: i for i, t in enumerate(ts.terms)}
    first = {}
    for source, lag in lin:
        first.setdefault(source, lag)
    top = ts.order
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
            out.append((k, mask))
    return out

"""One call from measured signals to a fitted model: the public entry point.

``identify(u=..., y=...)`` validates the data once (here, at the boundary),
builds the regression matrix, runs the GA with single parent mating on the
chosen criterion and fits the winning structure by QR least squares.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from ..memory import check_memory
from .criteria import Criterion, get_criterion
from .evaluator import StructureEvaluator
from .ga import GAConfig, GAResult, GenerationStats, run_ga
from .model import NarxModel
from .problem import excluded_columns
from .refine import refine_simulation
from .segments import normalise_segments, usable_segments
from .terms import TermSpace, power_of_two_scale

__all__ = ["FOCUS", "IdentificationResult", "check_samples", "identify",
           "select_for_simulation", "validate_signals"]

#: What a model is selected and fitted for.
FOCUS = ("prediction", "simulation")

#: Levenberg-Marquardt evaluations per move of the simulation-focused local search
#: (warm-started from the neighbour; the winner is then refined to convergence).
SEARCH_STEPS = 30


@dataclass
class IdentificationResult:
    """A fitted model and the search that produced it."""

    model: NarxModel
    ga: GAResult
    criterion: str
    seed: int | None



#: In larger term spaces the data need rows for structures of this many terms only.
LARGE_SPACE = 100


def check_samples(n_samples: int, max_lag: int, n_terms: int = 1) -> None:
    """Raise DataError when there are too few samples to fit with these lags.

    A fit needs more regression rows (``n_samples - max_lag``) than the largest
    possible structure has terms.
    """
    rows = n_samples - max_lag
    if rows <= n_terms:
        raise DataError(
            f"too few samples: {n_samples} samples give {max(rows, 0)} regression rows "
            f"with maximum lag {max_lag}, but {n_terms + 1} or more are needed for "
            f"{n_terms} candidate terms (need at least {max_lag + n_terms + 1} samples)"
        )


def validate_signals(u, y, term_space: TermSpace,
                     segments: list[tuple[int, int]] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert u, y at the public boundary.

    Raises
    ------
    DataError
        Not 1-D, different lengths, non-finite values, or too few samples.
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    m = term_space.n_inputs
    if y.ndim != 1 or not (u.ndim == 1 and m == 1 or u.ndim == 2 and u.shape[1] == m):
        raise DataError(f"y must be 1-D and u of shape (n,) or (n, {m}) for {m} input(s) "
                        f"{', '.join(term_space.inputs)}; got shapes {u.shape} and {y.shape}")
    if len(u) != len(y):
        raise DataError(f"u and y must have the same length, got {len(u)} and {len(y)}")
    for name, arr in (("u", u), ("y", y)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise DataError(
                f"{name} has {bad.size} non-finite value(s) (NaN or inf), first at index "
                f"{bad[0]}"
            )
    # Rows for the largest structure of the space -- or, in spaces of more than
    # LARGE_SPACE terms, for structures of LARGE_SPACE terms: larger ones simply cannot
    # be fitted on this data (rank-deficient, never selected).
    need = min(term_space.n_terms, LARGE_SPACE)
    if segments is None:
        check_samples(len(y), term_space.max_lag, need)
    else:
        rows = sum(b - a - term_space.max_lag for a, b in segments)
        if rows <= need:
            raise DataError(
                f"too few samples: {len(segments)} segment(s) longer than the largest lag "
                f"({term_space.max_lag}) give {max(rows, 0)} regression rows, but "
                f"{need + 1} or more are needed for {term_space.n_terms} candidate terms")
    check_magnitudes(u, y, term_space)
    return u, y


#: Largest and smallest RMS of the output that squared sums (SSE, MSE) still hold.
Y_RMS_RANGE = (1e-150, 1e150)


def check_magnitudes(u: np.ndarray, y: np.ndarray, term_space: TermSpace) -> None:
    """Refuse signals whose magnitudes double precision cannot carry through a fit.

    Fits run on data scaled by powers of two (exact), but the SSE, the MSE and
    the coefficients are reported in the user's units: the output's RMS must lie
    in :data:`Y_RMS_RANGE` (else its squared sums under- or overflow), and every
    coefficient's unit factor (output scale over input and output scales to the
    term's powers) must be a normal float.

    Raises
    ------
    DataError
        Naming the signal, its RMS and what to do.
    """
    def rms(x):
        x = np.asarray(x, dtype=float)
        peak = float(np.max(np.abs(x))) if x.size else 0.0
        return peak * float(np.sqrt(np.mean(np.square(x / peak)))) if peak > 0 else 0.0

    ry = rms(y)
    low, high = Y_RMS_RANGE
    if ry > 0 and not low <= ry <= high:
        raise DataError(
            f"the output {term_space.output} has RMS {ry:.1e}: beyond {low:.0e}..{high:.0e}, "
            "its squared errors cannot be represented in double precision; rescale it "
            f"(e.g. multiply by 1e{-int(np.floor(np.log10(ry)))}) and scale the model's "
            "output back")
    u2 = term_space.inputs_2d(u)
    su = np.array([power_of_two_scale(c) for c in u2.T])
    factors = term_space.coefficient_factors(su, power_of_two_scale(y))
    tiny = np.finfo(float).tiny
    bad = ~(np.isfinite(factors) & (factors >= tiny))
    if bad.any():
        term = term_space.term_names()[int(np.flatnonzero(bad)[0])]
        sizes = ", ".join(f"{n} {rms(c):.1e}" for n, c in zip(term_space.inputs, u2.T))
        raise DataError(
            f"the signals' magnitudes (RMS: {sizes}; {term_space.output} {ry:.1e}) are too far "
            f"apart for the coefficients of terms such as {term} to be represented in double "
            "precision; rescale the inputs and the output to similar magnitudes")


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
        Progress hook, see :func:`spm_sysid.core.narx.ga.run_ga`.
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
    term_space = term_space or TermSpace()
    crit = get_criterion(criterion)
    if focus not in FOCUS:
        raise ValueError(f"focus must be one of {', '.join(FOCUS)}, got {focus!r}")
    if segments is not None:
        segments = normalise_segments(segments, len(np.asarray(y)))
        segments, _, _ = usable_segments(segments, term_space.max_lag)
        if not segments:
            raise DataError(f"no segment of the data is longer than the largest lag "
                            f"({term_space.max_lag}): nothing to fit")
    u, y = validate_signals(u, y, term_space, segments)
    if not np.any(y):
        raise DataError("the output y is zero throughout: there is nothing to identify")
    ga = ga or GAConfig()
    rows = len(y) - term_space.max_lag if segments is None else sum(
        b - a - term_space.max_lag for a, b in segments)
    # the matrix, its scaled copy in the evaluator and the QR work space, with margin,
    # plus the evaluator's Gram matrix and triangular factor of all candidate terms
    m = term_space.n_terms
    check_memory(5 * 8 * rows * (m + 1) + 2 * 8 * (m + 2) ** 2,
                 f"the regression matrix of {rows} rows x {m} candidate terms")
    u2 = term_space.inputs_2d(u)
    su = np.array([power_of_two_scale(c) for c in u2.T])
    sy = power_of_two_scale(y)
    P, target = term_space.regression(u2 / su, y / sy, segments)
    zero, duplicate_of = excluded_columns(P)
    nonzero = ~zero & (duplicate_of < 0)
    names = term_space.term_names()
    excluded = [names[i] for i in np.flatnonzero(zero)]
    duplicates = {names[i]: names[duplicate_of[i]] for i in np.flatnonzero(duplicate_of >= 0)}
    evaluator = StructureEvaluator(P[:, nonzero], target, crit, sse_scale=sy * sy)
    result = run_ga(evaluator, ga, seed=seed, callback=callback)
    if not np.isfinite(result.best_score):
        raise DataError(
            "no structure could be fitted: every structure the search tried has linearly "
            "dependent regressors on this data (repeated or constant signals?)"
        )
    certificate = None
    if certify_time_limit is not None:
        certificate = _certify_search(evaluator, result, crit, certify_time_limit,
                                      [names[i] for i in np.flatnonzero(nonzero)])
    full_mask = np.zeros(term_space.n_terms, dtype=bool)
    full_mask[np.flatnonzero(nonzero)] = result.best_mask
    result.best_mask = full_mask
    info = {
        "ga": ga.to_dict(),
        "seed": seed,
        "generations_run": len(result.history) - 1,
        "first_best_generation": result.first_best_generation,
        "evaluations": result.evaluations,
        "search_seconds": round(result.elapsed, 4),
        "focus": focus,
        **({"excluded_zero_terms": excluded} if excluded else {}),
        **({"excluded_duplicate_terms": duplicates} if duplicates else {}),
        **({"certificate": certificate} if certificate is not None else {}),
    }
    if focus == "simulation":
        ranked = evaluator.ranked(shortlist)
        masks = np.zeros((len(ranked), term_space.n_terms), dtype=bool)
        masks[:, np.flatnonzero(nonzero)] = ranked
        model = select_for_simulation(u, y, term_space, masks, crit, segments=segments,
                                      metadata=info)
    else:
        model = NarxModel.fit(u, y, full_mask, term_space, segments=segments,
                              criterion=crit.name, criterion_value=result.best_score,
                              metadata=info)
    return IdentificationResult(model=model, ga=result, criterion=crit.name, seed=seed)


def select_for_simulation(
    u: np.ndarray, y: np.ndarray, term_space: TermSpace, candidates: np.ndarray,
    criterion: Criterion, *, segments: list[tuple[int, int]] | None = None,
    metadata: dict | None = None, max_passes: int = 10,
) -> NarxModel:
    """The structure and coefficients that simulate best, by an information criterion.

    Each candidate structure (rows of ``candidates``, e.g. the GA's best by the
    one-step criterion) is fitted by least squares, refined on its free-run error
    (:func:`~spm_sysid.core.narx.refine.refine_simulation`) and scored by
    ``criterion`` with the free-run SSE in place of the one-step SSE (so AIC
    becomes ``N ln(SSE_sim / N) + 2k``). From the best, a local search removes
    or adds one term at a time (terms of the candidates; every term in spaces of
    at most 100) while that lowers the simulation criterion. Structures whose
    simulation diverges on the estimation data are never returned.

    Raises
    ------
    DataError
        When every candidate's simulation diverges on the estimation data.
    """
    lag0 = term_space.max_lag
    P, target = term_space.regression(u, y, segments)
    norms = np.linalg.norm(P, axis=0)
    y_norm = float(np.linalg.norm(target)) or 1.0
    rows = len(target)
    scored: dict[bytes, tuple[float, NarxModel | None]] = {}
    refinements = 0

    def score(mask: np.ndarray, start: NarxModel | None = None) -> float:
        nonlocal refinements
        key = np.packbits(mask).tobytes()
        if key in scored:
            return scored[key][0]
        value, model = np.inf, None
        if mask.any():
            try:
                model = NarxModel.fit(u, y, mask, term_space, segments=segments)
            except ValueError:  # linearly dependent on this data
                model = None
        if model is not None:
            if start is not None:  # warm start: a neighbour's refined coefficients
                theta = dict(zip(start.term_indices, start.coefficients))
                warm = np.array([theta.get(i, 0.0) for i in model.term_indices])
                ls = model.coefficients
                model.coefficients = warm
                ref = refine_simulation(model, u, y, segments, max_evaluations=SEARCH_STEPS)
                if not ref.success:
                    model.coefficients = ls
                    ref = refine_simulation(model, u, y, segments)
            else:
                ref = refine_simulation(model, u, y, segments)
            refinements += 1
            if ref.success and np.isfinite(ref.sse):
                model.coefficients = ref.coefficients
                beta = np.zeros((1, term_space.n_terms))
                beta[0, mask] = ref.coefficients * norms[mask] / y_norm
                v = float(criterion(np.array([max(ref.sse, 1e-300)]), rows,
                                    np.array([mask.sum()]), beta)[0])
                value = v if np.isfinite(v) else np.inf
                model.metadata = {"refinement": ref.message, "free_run_sse": ref.sse,
                                  "least_squares_free_run_sse": ref.sse_start}
        scored[key] = (value, model)
        return value

    for mask in candidates:
        score(mask)
    if not scored or min(v for v, _ in scored.values()) == np.inf:
        raise DataError("every candidate structure's free-run simulation diverges on the "
                        "estimation data (or cannot be fitted): no model simulates")
    best_key = min(scored, key=lambda k: scored[k][0])
    best = np.unpackbits(np.frombuffer(best_key, dtype=np.uint8))[:term_space.n_terms]
    best = best.astype(bool)
    pool = (np.ones(term_space.n_terms, dtype=bool) if term_space.n_terms <= 100
            else candidates.any(axis=0))
    passes = 0
    while passes < max_passes:
        passes += 1
        value, current = scored[np.packbits(best).tobytes()]
        moves = []
        for j in np.flatnonzero(pool):
            trial = best.copy()
            trial[j] = not trial[j]
            moves.append((score(trial, current), j))
        v, j = min(moves, default=(np.inf, -1))
        if not v < value:
            break
        best[j] = not best[j]
    value, model = scored[np.packbits(best).tobytes()]
    # the search's moves ran a few Levenberg-Marquardt steps each: finish the winner's
    final = refine_simulation(model, u, y, segments)
    refinements += 1
    if final.success and final.sse < model.metadata["free_run_sse"]:
        model.coefficients = final.coefficients
        beta = np.zeros((1, term_space.n_terms))
        beta[0, best] = final.coefficients * norms[best] / y_norm
        value = float(criterion(np.array([max(final.sse, 1e-300)]), rows,
                                np.array([best.sum()]), beta)[0])
        model.metadata["free_run_sse"] = final.sse
    one_step = model.residuals(u, y, segments)
    model.mse = float(one_step @ one_step) / len(one_step)
    model.criterion, model.criterion_value = criterion.name, value
    model.n_samples = len(y) if segments is None else sum(
        b - a for a, b in segments if b - a > lag0)
    model.metadata = {**(metadata or {}), "simulation": {
        **model.metadata, "candidates": len(candidates), "refinements": refinements,
        "local_search_passes": passes,
        "criterion_meaning": f"{criterion.name.upper()} of the free-run simulation error "
                             "(SSE of the simulated output) on the estimation data"}}
    return model


def _certify_search(evaluator: StructureEvaluator, result: GAResult, crit: Criterion,
                    time_limit: float, names: list[str]) -> dict:
    """Certify the GA's result in place (a better structure found replaces it)."""
    from .certify import certify

    try:
        cert = certify(None, None, crit, warm_start=result.best_mask, time_limit=time_limit,
                       evaluator=evaluator)
    except ValueError as exc:  # a criterion that cannot be certified
        return {"status": "refused", "reason": str(exc)}
    cert.terms = [names[i] for i in np.flatnonzero(cert.mask)]
    doc = cert.to_dict()
    doc["ga_value"] = float(result.best_score)
    if cert.value < result.best_score:
        result.best_mask, result.best_score = cert.mask.copy(), cert.value
    return doc

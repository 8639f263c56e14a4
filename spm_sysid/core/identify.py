"""From a record to a fitted model: the identification pipeline, written once.

::

    signals + term space --Problem.from_signals--> Problem (checked, scaled, built once)
        --data check--> GA with SPM (run_ga) --> polish --> plan (plan_selection)
        --> [certification] --> choose (the plan's selector) --> model, its account

``identify(u=..., y=...)`` is the public entry; :func:`identify_problem` is the
same on a problem already built (a study's runs share one problem per process,
so a study run is exactly the computation ``identify`` does). Both read their
settings from one :class:`~spm_sysid.core.options.SearchOptions`.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .blas import one_blas_thread
from .defaults import AUTO_CERTIFY_TERMS, RESTART_TERMS
from .errors import DataError, SettingsError
from .fit.criteria import CERTIFIABLE, Criterion, get_criterion
from .fit.problem import Problem, check_samples, validate_signals
from .model.narx import NarxModel
from .model.operating_point import (
    OperatingPoint,
    choose_operating_point,
    in_record_units,
    own_sign_at,
)
from .model.terms import TermSpace
from .options import SEARCH_SETTINGS, SearchOptions
from .progress import Progress, ProgressFn
from .search.ga import GAConfig, GAResult, GenerationStats, run_ga
from .search.local import PolishResult, polish
from .search.neighbourhood import MoveScreen
from .search.ties import lowest_degree_of_ties
from .select.choose import choose, overfit_warnings, selection_account
from .select.folds import is_long
from .select.plan import SelectionPlan, plan_selection
from .select.simulation import select_for_simulation
from .settings import SETTINGS
from .settings import check as check_setting
from .validate.constancy import constancy, constancy_warnings

__all__ = ["FOCUS", "SELECTION", "IdentificationResult", "check_samples", "identify",
           "identify_problem", "select_for_simulation", "validate_signals"]

#: What a model is selected and fitted for (the schema's choices of ``focus``).
FOCUS = SETTINGS["focus"].choices

#: How a structure is chosen (the schema's choices of ``selection``).
SELECTION = SETTINGS["selection"].choices

#: The term space's and the GA's settings, which ``identify`` also takes by name.
_SPACE_SETTINGS = ("ny", "nu", "degree", "delay", "constant")
_GA_SETTINGS = ("population_size", "generations", "crossover_prob", "mutation_prob",
                "spm_fraction", "fitness", "init_terms", "mutation_per_structure", "elitism")


@dataclass
class IdentificationResult:
    """A fitted model, the search that produced it, and the problem it was fitted on."""

    model: NarxModel
    ga: GAResult
    problem: Problem | None = None


def identify(
    *, u: np.ndarray, y: np.ndarray, term_space: TermSpace | None = None,
    ga: GAConfig | None = None, segments: list[tuple[int, int]] | None = None,
    callback: Callable[[GenerationStats], bool | None] | None = None,
    progress: ProgressFn | None = None, **settings: Any,
) -> IdentificationResult:
    """Select a NARX structure with the SPM-GA and fit it.

    Parameters
    ----------
    u, y : ndarray, shapes (n,) or (n, m), and (n,)
        Input samples (one column per input) and output samples, equally spaced.
    term_space, ga : TermSpace, GAConfig, optional
        Default: the paper's (ny=4, nu=4, degree 2, delay 1; population 200, 300
        generations, SPM 0.15), or those of the settings given by name.
    segments : list of (start, stop), optional
        Contiguous parts (no regression row crosses a gap; parts no longer than
        the largest lag skipped); default: the whole record.
    callback, progress : callable, optional
        Called with each generation's statistics (``False`` stops the search,
        :func:`run_ga`), and with :class:`~spm_sysid.core.progress.Progress` records.
    **settings
        Any job setting of the schema (:mod:`spm_sysid.core.settings`, ``spm-sysid
        settings``) by its name, checked here once: ``criterion`` (a name, or a
        :class:`~spm_sysid.core.fit.criteria.Criterion` or a user's ``f(sse, n, k,
        coefficients)``), ``seed``, ``focus``, ``selection``, ``shortlist``,
        ``max_terms``, ``polish``, ``certify``, ``certify_time_limit``,
        ``auto_certify_time_limit``, ``horizon``, ``operating_point``, ``orders``
        (``auto``: proposed from the data), ``decimate`` (at 1/N of the rate), the
        term space's and the GA's. A ``certify_time_limit`` given alone asks for the
        certification. The validation's settings are refused: validation is
        :func:`~spm_sysid.core.validate.validation.validate_model`'s (or a job's).

    Raises
    ------
    SettingsError, DataError
        An unknown or validation setting, a value out of range; data that cannot
        identify the space (:meth:`Problem.from_signals`).

    Notes
    -----
    u and y are scaled by powers of two (exact), so data of any magnitude identify
    alike; data far from zero are identified around their means
    (:mod:`~spm_sysid.core.model.operating_point`); coefficients and criteria are in
    the user's units. Terms zero on all rows, or repeating an earlier term, are left
    out (``metadata["excluded_zero_terms"]``, ``["excluded_duplicate_terms"]``).
    """
    u, y, segments, decimation = _decimated(u, y, segments, settings.pop("decimate", None))
    around = settings.pop("operating_point", "auto")
    options, term_space, ga, orders, regressors = _edge(settings, term_space, ga)
    point, kept_as_is = _operating_point(around, u, y, segments, term_space, regressors)
    u, y, space, why = _space(u, y, segments, term_space, options, orders, regressors, point)
    result = identify_problem(Problem.from_signals(u, y, space, segments), options, ga=ga,
                              callback=callback, progress=progress)
    result.model = model = (result.model if point is None
                            else in_record_units(result.model, point))
    model.metadata.update({k: v for k, v in (("orders", why), ("decimation", decimation),
                                             ("operating_point", kept_as_is and {
                                                 "reason": kept_as_is})) if v})
    return result


def _space(u, y, segments, term_space: TermSpace, options: SearchOptions, orders: str,
           regressors: list[str], point: OperatingPoint | None):
    """The signals to fit (their deviations from ``point``), the space, why its orders.

    The orders proposed from those signals when ``orders`` is ``auto``; the
    regressors added; the constant a candidate around an operating point (a
    model of the deviations may need it).
    """
    if point is not None:
        u, y = point.centred(u, y)
    term_space, why = (_orders_from_data(u, y, segments, term_space, options)
                       if orders == "auto" else (term_space, None))
    if regressors:
        term_space = _with_regressors(term_space, regressors, y, u, own_sign_at(point))
    if point is not None:
        term_space = replace(term_space, constant=True)
    return u, y, term_space, why


def _operating_point(setting: str, u, y, segments, term_space: TermSpace,
                     regressors: list[str]) -> tuple[OperatingPoint | None, str | None]:
    """The point ``identify`` works around (None: the record as it is), and why not if not."""
    from .model.segments import normalise_segments

    setting = check_setting("operating_point", setting)
    y, u = np.asarray(y, dtype=float), np.asarray(u, dtype=float)
    if (y.ndim != 1 or u.ndim not in (1, 2) or len(u) != len(y) or not np.all(np.isfinite(y))
            or not np.all(np.isfinite(u))):
        return None, None  # the problem's checks say what is wrong
    u = u.reshape(len(y), -1)
    rows = [slice(a, b) for a, b in normalise_segments(segments, len(y))]
    u_rows, y_rows = np.concatenate([u[r] for r in rows]), np.concatenate([y[r] for r in rows])
    if len(y_rows) < 2 or term_space.n_inputs != u.shape[1]:
        return None, None
    space = (_with_regressors(term_space, regressors, y, u, False if setting == "mean" else None)
             if regressors else term_space)
    return choose_operating_point(setting, u_rows, y_rows, space)


def _decimated(u, y, segments, factor: int | None):
    """The arrays decimated by ``factor`` inside their segments, the segments, the account.

    As a job decimates its record (:meth:`~spm_sysid.core.record.Record.decimated`);
    a factor of None or 1 leaves them as they are (no account).
    """
    from .model.decimation import decimate_blocks, decimation_doc
    from .model.segments import normalise_segments

    if factor is None or check_setting("decimate", factor) == 1:
        return u, y, segments, None
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    bounds = normalise_segments(segments, len(y))
    u2, y2, out, _ = decimate_blocks(u, y, bounds, factor)
    doc = decimation_doc(factor, len(y), len(y2), sum(b - a for a, b in bounds))
    return u2, y2, [b for b in out if b[1] > b[0]], doc


def _with_regressors(term_space: TermSpace, regressors: list[str], y, u,
                     own_sign: bool | None = None) -> TermSpace:
    """The term space with ``regressors`` added (presets take their scales from y, u).

    ``own_sign``: see :func:`~.model.presets.expand_presets` (False: y, u around a point).
    """
    from .model.presets import expand_presets, preset_inputs

    try:
        return replace(term_space, regressors=term_space.regressors + tuple(
            expand_presets(regressors, term_space.output, y, preset_inputs(term_space, u),
                           term_space.ny, own_sign)))
    except ValueError as exc:
        raise SettingsError(f"regressors: {exc}") from None


def _orders_from_data(u: np.ndarray, y: np.ndarray, segments: list[tuple[int, int]] | None,
                      term_space: TermSpace, options: SearchOptions) -> tuple[TermSpace, dict]:
    """``orders: auto``: the lags and degree proposed from the data, and why."""
    from .model.segments import normalise_segments
    from .validate.orders import orders_from_data

    u2 = np.asarray(u, dtype=float)
    criterion = options.criterion if isinstance(options.criterion, str) else "bic"
    return orders_from_data(u2 if u2.ndim == 2 else u2[:, None], np.asarray(y, dtype=float),
                            normalise_segments(segments, len(y)), term_space, criterion,
                            options.focus)


def _edge(settings: dict, term_space, ga
          ) -> tuple[SearchOptions, TermSpace, GAConfig, str, list[str]]:
    """The Python API's settings, checked once by the schema (see :func:`identify`)."""
    from .settings import check

    given = {k: v for k, v in settings.items() if v is not None}
    known = set(SEARCH_SETTINGS) | {"orders", "simulation_folds", "simulation_repeats",
                                    "regressors", *_SPACE_SETTINGS, *_GA_SETTINGS}
    validation = {n for n, s in SETTINGS.items() if s.group == "validation"}
    timeline = {n for n, s in SETTINGS.items() if s.group == "data"}
    for name in given:
        if name in validation and name not in known:
            raise SettingsError(f"identify() does not validate: {name} is a setting of the "
                                "validation (validate_model, or run_job for a whole job)")
        if name in timeline and name not in known:
            raise SettingsError(f"identify() takes samples without stamps: {name} is a "
                                "setting of a record's timeline (give segments, or run_job "
                                "with a Record)")
        if name not in known:
            raise SettingsError(f"identify() has no setting {name!r} (spm-sysid settings "
                                "lists them all)")
    if "certify_time_limit" in given and "certify" not in given:
        given["certify"] = True
    space = {k: given.pop(k) for k in _SPACE_SETTINGS if k in given}
    gas = {k: given.pop(k) for k in _GA_SETTINGS if k in given}
    if space and term_space is not None or gas and ga is not None:
        raise SettingsError("give the term space (or the GA) as an object or by its "
                            "settings, not both")
    term_space = TermSpace(**space) if space else (term_space or TermSpace())
    ga = GAConfig(**gas) if gas else (ga or GAConfig())
    orders = check("orders", given.pop("orders", "given"))
    regressors = given.pop("regressors", None) or ()
    items = [regressors] if isinstance(regressors, str) else list(regressors)
    options = SearchOptions.from_values(given)
    get_criterion(options.criterion)  # a name that is not registered fails here
    return options, term_space, ga, orders, [t.strip() for item in items
                                             for t in str(item).split(";") if t.strip()]


@one_blas_thread()
def identify_problem(
    problem: Problem,
    options: SearchOptions | None = None,
    *,
    ga: GAConfig | None = None,
    callback: Callable[[GenerationStats], bool | None] | None = None,
    progress: ProgressFn | None = None,
    started: float | None = None,
    check_data: bool = True,
) -> IdentificationResult:
    """:func:`identify` on a problem already built, with checked options.

    ``options`` were checked at the edge (:func:`identify`, a job's
    :class:`~spm_sysid.core.jobs.settings.JobSettings`, a study's configuration).
    ``started`` is ``time.perf_counter()`` at the job's start (progress reports
    count their seconds from it; default: now). ``check_data``: run the data
    check (:mod:`spm_sysid.core.validate.excitation`) first; its warnings go into
    ``model.metadata["warnings"]``.
    """
    options = options or SearchOptions()
    drawn = options.seed is None
    if drawn:  # a new seed each run, written in the document: the run can be repeated
        options = options.with_seed(secrets.randbelow(2**31 - 1))
    crit = get_criterion(options.criterion)  # the name (checked at the edge) to its object
    started = time.perf_counter() if started is None else started
    report = progress or (lambda p: None)
    ga = ga or GAConfig()
    data_check = _check_data(problem, crit) if check_data else None
    evaluator = problem.evaluator(crit, max_terms=options.max_terms)
    plan = plan_selection(problem, options)
    result, polished = _searched(problem, evaluator, ga, options, plan, (callback, report),
                                 started)
    certificate = None
    within = _certify_within(plan, options, crit, problem)
    if within is not None:
        certificate = _certify_search(problem, evaluator, result, crit, within, report,
                                      started)
    _lowest_degree_of_ties(problem, evaluator, result, certificate)
    result.best_mask = problem.expand(result.best_mask)
    info = _search_account(problem, result, ga, options, plan, polished, certificate,
                           data_check, seed_drawn=drawn)
    model, chosen = choose(plan, problem, evaluator, result.best_mask, result.best_score,
                           crit, options, info, report, started)
    model.metadata["selection"] = selection_account(problem, plan, model, chosen)
    warnings = (data_check.warnings if data_check else []) + plan.warnings \
        + overfit_warnings(problem, model) + _constancy(problem, model)
    if warnings:
        model.metadata["warnings"] = warnings
    return IdentificationResult(model=model, ga=result, problem=problem)


def _constancy(problem: Problem, model: NarxModel) -> list[str]:
    """Whether the record's halves fit the returned structure alike; its warning if not."""
    found = constancy(model, problem.u, problem.y, problem.segments)
    if found is not None:
        model.metadata["constancy"] = found
    return constancy_warnings(found)


def _check_data(problem: Problem, crit: Criterion):
    from .validate.excitation import check_problem

    return check_problem(problem, criterion=crit.name)


def _searched(problem, evaluator, ga: GAConfig, options: SearchOptions, plan: SelectionPlan,
              calls, started) -> tuple[GAResult, dict | None]:
    """The GA and its polish; twice in mid-size spaces (:data:`RESTART_TERMS`), the better kept.

    Twice where the space has more usable terms than that, the record is not
    long and the criterion's optimum is the answer (``plan.mode`` ``criterion``):
    a validated selection judges the GA's structures on held-out data, and a
    second search only changed which of them it met (the heat exchanger's
    `--focus simulation --orders auto` on its first half went from a 44-term
    model, 0.480 on the second half, to a 5-term linear one, 0.700). ``calls``:
    the GA's callback and the progress function.

    The second GA draws from an independent stream of the same seed (numpy's
    ``SeedSequence`` spawned from it), so a run repeats with its seed; its phases
    are reported again (search, polish), the best so far never worse than the
    first's. The polish account then says what each search ended at and which was
    kept.
    """
    callback, report = calls
    result = _search(problem, evaluator, ga, options, callback, report, started)
    if not options.polish:
        return result, None
    polished = _polish(problem, evaluator, result, report, started)
    if (result.stopped_early or problem.usable.sum() <= RESTART_TERMS or is_long(problem)
            or plan.mode != "criterion" or not np.isfinite(result.best_score)):
        return result, polished
    first = float(result.best_score)

    def still_first(p: Progress) -> None:  # the best so far stays the first's until beaten
        report(replace(p, best=min(p.best, first)))

    stream = np.random.SeedSequence(options.seed, spawn_key=(1,))
    again = _search(problem, evaluator, ga, options, callback, still_first, started, stream)
    polished_again = _polish(problem, evaluator, again, still_first, started)
    second = float(again.best_score)
    ends = {"first": (first, result.best_mask.copy()), "second": (second, again.best_mask.copy())}
    if second < first - 1e-9:
        result, polished = again, polished_again
    kept = "second" if second < first - 1e-9 else "first"
    _greedy_polishes(problem, evaluator, ends, report, started)
    for name, (value, mask) in ends.items():
        if value < result.best_score - 1e-9:
            result.best_mask, result.best_score, kept = mask, value, name
    return result, {**polished, "value": float(result.best_score),
                    "restart": {**{k: v for k, (v, _) in ends.items()}, "kept": kept}}


def _greedy_polishes(problem: Problem, evaluator, ends: dict, report: ProgressFn,
                     started: float) -> None:
    """Three more polished starts beside the GA's two searches, added to ``ends``.

    ``ends``: ``{name: (value, mask)}`` of the searches so far (:func:`_searched`).
    Two greedy starts far from where the GA converges, deterministic (no seed):
    forward selection's end (``forward``), and every usable term (``all_terms``;
    the ranked descent removes terms first: backward elimination, with swaps).
    Then the terms the best end shares with the best other end (``common``): two
    good structures agree on what matters, and their difference is where a
    polish of one does not reach the other. At 84 candidates ((3, 3, 3) with the
    constant, first halves; docs/results.md) the greedy starts reach the best
    value known where 20 GA seeds of two searches each reached it 17 times (the
    dryer's BIC, from forward selection) and 8 times (the heat exchanger's BIC,
    from every term); the common terms take the heat exchanger's AIC from a
    basin 22 terms away. About 1.5 s each; the best reported never above the
    searches' best.
    """
    from .search.forward import forward_selection

    usable = np.zeros(evaluator.n_terms, dtype=bool)
    usable[_kick_terms(problem, evaluator)] = True
    floor = min(v for v, _ in ends.values())
    starts = [("forward", lambda: forward_selection(evaluator)[1]),
              ("all_terms", lambda: usable), ("common", lambda: _common_terms(ends))]
    for name, start in starts:
        mask = start()
        if mask is None or not mask.any():
            continue
        res = _polish_from(problem, evaluator, mask, None, report, started, floor)
        ends[name] = (float(res.value), res.mask.copy())
        floor = min(floor, float(res.value))


def _common_terms(ends: dict) -> np.ndarray | None:
    """The terms the best end shares with the best end of another structure (None: one)."""
    ranked = sorted(ends.values(), key=lambda end: end[0])
    best = ranked[0][1]
    other = next((mask for _, mask in ranked[1:] if not np.array_equal(mask, best)), None)
    return None if other is None else best & other


def _search(problem, evaluator, ga: GAConfig, options: SearchOptions, callback, report,
            started, seed: np.random.SeedSequence | None = None) -> GAResult:
    """The GA with SPM; a search that fits nothing is an error naming the likely cause.

    ``seed``: the GA's stream (default: the options' seed).
    """
    best_so_far = _best_so_far(problem, evaluator)

    def on_generation(stats: GenerationStats):
        report(Progress("search", stats.generation, ga.generations, stats.best,
                        stats.evaluations, elapsed=time.perf_counter() - started,
                        best_model=best_so_far))
        return None if callback is None else callback(stats)

    result = run_ga(evaluator, ga, seed=options.seed if seed is None else seed,
                    callback=on_generation)
    if np.isfinite(result.best_score):
        return result
    from .validate.excitation import describe_glitches, glitches

    glitch = describe_glitches(problem.y, glitches(problem.y, problem.segments),
                               problem.term_space.output)
    raise DataError(
        "no structure could be fitted: every structure the search tried has linearly "
        "dependent regressors on this data (" + (glitch or "repeated or constant signals?")
        + ")" + (f", or more than max_terms = {options.max_terms} terms"
                 if options.max_terms else ""))


def _certify_within(plan: SelectionPlan, options: SearchOptions, crit: Criterion,
                    problem: Problem) -> float | None:
    """Seconds of certification: asked for, or automatic on the paper's path; else None."""
    if options.certify_within is not None:
        return options.certify_within
    if (options.auto_certify_time_limit > 0 and plan.mode == "criterion"
            and options.focus == "prediction" and crit.name in CERTIFIABLE
            and problem.usable.sum() <= AUTO_CERTIFY_TERMS):
        return options.auto_certify_time_limit
    return None


def _search_account(problem, result: GAResult, ga: GAConfig, options: SearchOptions,
                    plan: SelectionPlan, polished, certificate, data_check, *,
                    seed_drawn: bool = False) -> dict:
    """What the search did, for the model document's metadata."""
    excluded = problem.excluded_terms()
    open_loop = plan.open_loop
    return {
        "ga": ga.to_dict(),
        "seed": options.seed,
        **({"seed_drawn": True} if seed_drawn else {}),
        "generations_run": len(result.history) - 1,
        "first_best_generation": result.first_best_generation,
        "evaluations": result.evaluations,
        "search_seconds": round(result.elapsed, 4),
        "focus": options.focus,
        **({"max_terms": options.max_terms} if options.max_terms else {}),
        **({"polish": polished} if polished is not None else {}),
        **({"excluded_zero_terms": excluded["zero"]} if excluded["zero"] else {}),
        **({"excluded_duplicate_terms": excluded["duplicate"]} if excluded["duplicate"]
           else {}),
        **({"excluded_regressor_products": excluded["regressor_products"]}
           if excluded["regressor_products"] else {}),
        **({"certificate": certificate} if certificate is not None else {}),
        **({"data_check": data_check.to_dict()} if data_check is not None else {}),
        **({"open_loop": {**open_loop.to_dict(),
                          **({"horizon": plan.horizon} if plan.horizon else {})}}
           if open_loop is not None else {}),
    }


#: Seconds between the polish's progress reports (at least).
POLISH_REPORT_EVERY = 0.5


def _best_so_far(problem: Problem, evaluator) -> Callable[[], NarxModel | None]:
    """Builds the best model the evaluator has scored so far (for a job stopped early)."""
    def best_so_far():
        best = evaluator.ranked(1)
        if not len(best):
            return None
        return problem.model(problem.expand(best[0]), criterion=evaluator.criterion.name,
                             criterion_value=float(evaluator.cached_score(best[0])))
    return best_so_far


def _polish(problem: Problem, evaluator, result: GAResult, report: ProgressFn,
            started: float) -> dict:
    """The polish (:func:`~spm_sysid.core.search.local.polish`) of the GA's best, in place.

    Reported as the phase ``polish`` (its work done of its budget). What it did,
    for the document.
    """
    ga_value = float(result.best_score)
    if not np.isfinite(ga_value):
        return {"ga_value": None, "value": None, "steps": 0, "structures": 0}
    res = _polish_from(problem, evaluator, result.best_mask, ga_value, report, started)
    if res.value < ga_value:
        result.best_mask, result.best_score = res.mask.copy(), res.value
    return {"ga_value": ga_value, "value": float(result.best_score), "steps": res.steps,
            "structures": res.scored, "kicks": res.kicks, "moves": list(res.moves),
            "stopped": res.stopped, "budget": res.budget}


def _polish_from(problem: Problem, evaluator, start: np.ndarray, value: float | None,
                 report: ProgressFn, started: float, floor: float = np.inf) -> PolishResult:
    """The polish of ``start`` (its ``value`` if known), reported as the phase ``polish``.

    At most twice a second; the best reported is never above ``floor`` (the best
    an earlier search found).
    """
    best_so_far, last = _best_so_far(problem, evaluator), -np.inf

    def on_kick(done: int, budget: int, best: float) -> None:
        nonlocal last
        now = time.perf_counter()
        if now - last >= POLISH_REPORT_EVERY:
            last = now
            report(Progress("polish", done, budget, min(best, floor), evaluator.evaluations,
                            elapsed=now - started, best_model=best_so_far))

    on_kick(0, 0, np.inf if value is None else value)
    screen = MoveScreen(evaluator) if MoveScreen.usable(evaluator) else None
    return polish(evaluator.score, start, np.ones(evaluator.n_terms, dtype=bool),
                  value=value, kick_terms=_kick_terms(problem, evaluator),
                  usable_terms=int(problem.usable.sum()), screen=screen, progress=on_kick)


def _kick_terms(problem: Problem, evaluator) -> np.ndarray:
    """The evaluator's columns of the problem's usable terms (the polish may flip these)."""
    return np.flatnonzero(problem.usable) if len(problem.usable) == evaluator.n_terms \
        else np.arange(evaluator.n_terms)


def _lowest_degree_of_ties(problem: Problem, evaluator, result: GAResult,
                           certificate: dict | None) -> None:
    """An exact fit's ties resolved to the lowest degree, in place (:mod:`.search.ties`).

    Only for criteria of the SSE and the size, which keep their value; a
    certificate then names the structure returned.
    """
    degrees = problem.term_space.term_degrees[problem.usable]
    if not (np.isfinite(result.best_score) and MoveScreen.usable(evaluator)
            and len(degrees) == evaluator.n_terms):
        return
    mask = lowest_degree_of_ties(evaluator, result.best_mask, degrees)
    if np.array_equal(mask, result.best_mask):
        return
    value = float(evaluator.score(mask[None, :])[0])
    if value <= result.best_score + 1e-9 * max(1.0, abs(result.best_score)):
        result.best_mask, result.best_score = mask, value
        if certificate is not None and certificate.get("terms") is not None:
            names = problem.term_space.term_names()
            certificate["terms"] = [names[i] for i in np.flatnonzero(problem.expand(mask))]


def _certify_search(problem: Problem, evaluator, result: GAResult, crit: Criterion,
                    time_limit: float, report: ProgressFn, started: float) -> dict:
    """Certify the GA's result in place (a better structure found replaces it)."""
    from .search.split import certify_split

    def on_nodes(nodes: int, best: float, lower: float) -> None:
        report(Progress("certification", nodes, 0, best, bound=lower,
                        elapsed=time.perf_counter() - started))

    try:
        cert = certify_split(evaluator, problem.constant_split(), warm_start=result.best_mask,
                             time_limit=time_limit, progress=on_nodes)
    except ValueError as exc:  # a criterion that cannot be certified
        return {"status": "refused", "reason": str(exc)}
    names = problem.term_space.term_names()
    cert.terms = [names[i] for i in np.flatnonzero(problem.expand(cert.mask))]
    doc = cert.to_dict()
    doc["ga_value"] = float(result.best_score)
    if cert.value < result.best_score:
        result.best_mask, result.best_score = cert.mask.copy(), cert.value
    return doc

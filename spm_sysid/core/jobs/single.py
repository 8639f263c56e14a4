"""One job of one output: a record in, a validated model out, with a typed result.

::

    Record --segments, split--> Problem --identify_problem--> model --validate--> JobResult

:func:`run_single_job` is the whole path for one output; a record of several
outputs goes through :mod:`spm_sysid.core.jobs.several`, which runs this path
per output, and :func:`spm_sysid.core.jobs.run.run_job` picks between them. The
result is a :class:`JobResult` (model, validation report, search statistics,
data account, timings) with the one summary formatter, :meth:`JobResult.summary`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from ..blas import one_blas_thread
from ..errors import DataError
from ..fit.problem import Problem
from ..identify import identify_problem
from ..model.decimation import decimation_phrase
from ..model.narx import NarxModel
from ..model.operating_point import (
    OperatingPoint,
    choose_operating_point,
    in_record_units,
    operating_point_words,
    own_sign_at,
)
from ..model.segments import describe_data, segment_report
from ..online.monitor import store_monitor_reference
from ..progress import Progress, ProgressFn
from ..record import Record
from ..search.certify import describe_certificate
from ..search.ga import GAResult
from ..validate.envelope import data_ranges
from ..validate.explained import set_explained_warning
from ..validate.validation import (
    ValidationReport,
    check_correlation_lags,
    split_segments,
    validate_model,
)
from .settings import JobSettings

__all__ = ["JobResult", "OutputResult", "choose_orders", "describe_selection",
           "run_single_job", "validation_segments"]


class OutputResult(NamedTuple):
    """One output of a job's result: what a page, a figure or a summary row shows of it."""

    name: str
    model: NarxModel
    report: ValidationReport | None
    history: list


@dataclass
class JobResult:
    """What a job produced.

    Attributes
    ----------
    model : NarxModel
        With ``metadata["data"]`` (the data account) and, when validated,
        ``metadata["validation"]``.
    report : ValidationReport or None
        None with ``validation="none"``.
    search : GAResult
        The GA run (best score, evaluations, history, seconds).
    data : dict
        Samples, segments, gaps ... (:func:`spm_sysid.core.model.segments.segment_report`).
    estimation_samples : int
        Samples the fit used.
    seconds : dict
        ``search``, ``validation`` and ``total`` wall-clock seconds.
    validation_segments : list of (start, stop)
        The samples the report validated on (as the job chose them: with
        ``orders: auto`` the lags, and so the rows, are the chosen space's).
    times : ndarray or None
        Seconds of the report's rows (from the record's stamps), None without
        stamps or validation.
    """

    model: NarxModel
    report: ValidationReport | None
    search: GAResult
    data: dict
    estimation_samples: int
    seconds: dict = field(default_factory=dict)
    validation_segments: list = field(default_factory=list)
    times: np.ndarray | None = None

    @property
    def residuals(self) -> np.ndarray:
        """One-step residuals of the validation rows (empty without validation)."""
        return np.empty(0) if self.report is None else self.report.residuals

    @property
    def per_output(self) -> list[OutputResult]:
        """The one output (a job of several outputs has one entry each: the same view)."""
        return [OutputResult(self.model.term_space.output, self.model, self.report,
                             self.search.history)]

    @property
    def cross_tests(self) -> list:
        """The outputs' residual cross-correlation: none for one output."""
        return []

    @property
    def diverged(self) -> list[str]:
        """The output, when its free-run simulation left the measured range."""
        r = self.report
        return [self.model.term_space.output] if r is not None and r.diverged_at is not None \
            else []

    def summary(self, style: str = "lines") -> str:
        """The one summary formatter.

        ``"line"``: one paragraph (the node's answer, logs). ``"lines"``: the
        command line's block (equation, criterion, selection, coefficients with
        their intervals, warnings, validation).
        """
        m, crit = self.model, self.model.criterion.upper()
        value = m.criterion_value
        if m.metadata.get("focus") == "simulation":
            crit += " (simulation)"
        cert, selected = _certificate_words(m.metadata), _selection_words(m.metadata)
        warnings = m.metadata.get("warnings") or []
        if style == "line":
            text = (f"{m.equation()} | {crit} {value:.2f}, {len(m.term_indices)} terms, "
                    f"one-step MSE {m.mse:.4e}, {describe_data(self.data)}"
                    + decimation_phrase(m.metadata.get("decimation")))
            text += "".join(f", {part}" for part in (selected, cert) if part)
            if self.report is not None:
                text += f" ({_validation_words(self.report)})"
            if warnings:
                text += "; WARNING: " + "; WARNING: ".join(warnings)
            return text + f", {self.seconds.get('total', 0.0):.2f} s" + _seed_words(
                m.metadata, "the setting seed={seed}")
        lines = [m.equation(),
                 f"criterion {crit} = {value:.2f}, {len(m.term_indices)} terms, one-step MSE "
                 f"{m.mse:.4e}, {m.n_samples} samples, "
                 f"{self.seconds.get('search', self.search.elapsed):.2f} s "
                 f"({self.search.evaluations} structures fitted, cache hit rate "
                 f"{self.search.cache_hit_rate:.0%}{_seed_words(m.metadata)})"]
        lines += [part for part in (selected, cert) if part]
        lines.append(m.coefficient_table())
        lines += [f"warning: {w}" for w in warnings]
        if self.report is not None:
            lines.append(self.report.summary())
        return "\n".join(lines)


def _seed_words(meta: dict, repeat: str = "--seed {seed}") -> str:
    """A drawn seed, and how to repeat the run with it (``repeat``: the command's words)."""
    seed = meta.get("seed")
    return f"; seed {seed}, drawn: {repeat.format(seed=seed)} repeats this run" \
        if meta.get("seed_drawn") and seed is not None else ""


def _certificate_words(meta: dict) -> str:
    """The certificate in words, after what the polish improved (if it did)."""
    cert = describe_certificate(meta.get("certificate"))
    if cert and meta.get("excluded_regressor_products"):
        cert += (f"; the {meta['excluded_regressor_products']} products of two regressors "
                 "are not candidates")
    pol = meta.get("polish") or {}
    again = pol.get("restart")
    if again:
        greedy = "".join(f", the polish from {words} at {again[key]:.2f}" for key, words in
                         (("forward", "forward selection"), ("all_terms", "every term"),
                          ("common", "the best ends' common terms"))
                         if again.get(key) is not None)
        kept = {"forward": "forward selection's", "all_terms": "every term's",
                "common": "common terms'"}.get(
            again["kept"], again["kept"])
        cert = (f"a second GA and polish from another seed stream ended at "
                f"{again['second']:.2f}, the first at {again['first']:.2f}{greedy}: the "
                f"{kept} kept" + (f"; {cert}" if cert else ""))
    if pol.get("value") is not None and pol["value"] < pol["ga_value"]:
        cert = (f"the polish after the GA improved its best from {pol['ga_value']:.2f} "
                f"({pol['steps']} step(s))" + (f", {cert}" if cert else ""))
    return cert


def _selection_words(meta: dict) -> str:
    """How the structure was chosen, after the orders taken from the data (if they were)."""
    selected = describe_selection(meta.get("selection"))
    point = operating_point_words(meta.get("operating_point"))
    if point:
        selected = point + (f"; {selected}" if selected else "")
    orders = meta.get("orders")
    if orders:
        selected = (f"orders from the data: ny = nu = {orders['ny']}, degree "
                    f"{orders['degree']} ({orders['reason']})"
                    + (f"; {selected}" if selected else ""))
    return selected


def _validation_words(r) -> str:
    """The validation in one clause: fits, divergence, correlation tests."""
    o, f = r.one_step_metrics, r.free_run_metrics
    failed = [t.name for t in r.tests if not t.passed]
    free = (f"free-run DIVERGED at sample {f['diverged_at']}"
            if f.get("diverged_at") is not None
            else f"free-run fit {f['fit_percent']:.1f} %")
    tests = ("correlation tests not computed" if r.tests_skipped else
             "correlation tests " + ("all inside the band" if not failed
                                     else "outside the band: " + ", ".join(failed)))
    return f"{r.segment} validation: one-step fit {o['fit_percent']:.1f} %, {free}, {tests}"


def describe_selection(doc: dict | None) -> str:
    """How the structure was chosen, in a few words ('' when the document has nothing)."""
    if not doc:
        return ""
    if doc.get("method") == "coupled":
        return (f"chosen with the other outputs on their coupled free run over "
                f"{doc['folds']} held-out blocks: {doc.get('chosen')} ({doc.get('fitted')}); "
                "this output's own selection was not kept")
    if doc.get("method") == "validated":
        held = doc.get("held_out_mse")
        text = (f"selected by its {doc['what']} error on {doc['folds']} held-out blocks "
                + (f"(MSE {held:.4g})" if held is not None else ""))
        call = doc.get("linear_or_nonlinear") or {}
        if call.get("terms") is not None:  # what was returned, after guard and fallback
            text += f": a {call['choice']} model of {call['terms']} terms"
        if call.get("p_value") is not None:
            text += ("; the nonlinear candidate"
                     + (f" ({call['nonlinear_terms']} terms)" if call.get("nonlinear_terms")
                        else "")
                     + f" had {call['ratio']:.2f}x the best linear's held-out error "
                     f"(p = {call['p_value']:.3g}): " + _fate(call))
        elif call.get("choice") == "linear":
            text += "; no nonlinear finalist simulated the held-out blocks better than linear"
        if call.get("linear_arx_held_out_mse") is not None:
            text += (f"; the linear ARX (least squares, order {call['linear_arx_order']}) "
                     f"had MSE {call['linear_arx_held_out_mse']:.4g} on the same blocks")
        left = doc.get("left_range_held_out")
        if left:
            text += (f"; {left} finalist(s) left the output's range on the held-out blocks")
        removed = doc.get("removed_by_guard")
        if removed:
            text += (f"; the stability guard removed {removed} structure(s) whose simulation "
                     "left the output's range off the estimation data")
        return text
    return f"selected by the criterion on the estimation data ({doc.get('note', '')})"


def _fate(call: dict) -> str:
    """What became of the tested nonlinear candidate, in a clause."""
    fate = call.get("challenger_fate")
    if fate is None:  # documents written before the account described the returned model
        return ("better than the best linear one by more than the noise"
                if call.get("choice") == "nonlinear" else
                "not better than the best linear one by more than the noise: linear kept")
    if fate.startswith("returned"):
        return "better than the best linear one by more than the noise, " + fate
    if fate.startswith("removed"):
        return ("better than the best linear one by more than the noise, but " + fate
                + "; the model above was returned instead")
    return fate + ": linear kept"


def choose_orders(record: Record, settings: JobSettings, est, u: np.ndarray | None = None,
                  y: np.ndarray | None = None) -> tuple[JobSettings, dict]:
    """``orders: auto``: the settings with the lags and degree proposed from the data, and why.

    The proposal runs on the longest estimation segment
    (:func:`~spm_sysid.core.validate.orders.orders_from_data`) of the record's
    samples, or of ``u`` and ``y`` (its deviations from an operating point).
    """
    from ..validate.orders import orders_from_data

    space, why = orders_from_data(record.u if u is None else u, record.y if y is None else y,
                                  est, settings.term_space, settings.criterion, settings.focus)
    return replace(settings, term_space=space), why


def _operating_point(settings: JobSettings, u: np.ndarray, y: np.ndarray, est
                     ) -> tuple[OperatingPoint | None, str | None]:
    """The point the job identifies around (None: the record as it is), and why not if not.

    Decided on the estimation rows, with the regressors the job will add.
    """
    space = settings.term_space
    if settings.regressors and settings.operating_point != "none":
        space = settings.with_regressors(_rows(y, est), _rows(u, est), own_sign=(
            False if settings.operating_point == "mean" else None)).term_space
    return choose_operating_point(settings.operating_point, _rows(u, est), _rows(y, est), space)


def _in_units(report: ProgressFn, point: OperatingPoint | None) -> ProgressFn:
    """``report`` whose best model so far is written in the record's units."""
    if point is None:
        return report

    def mapped(p: Progress) -> None:
        built = p.best_model
        if built is None:
            return report(p)

        def best():
            model = built()
            return None if model is None else in_record_units(model, point)
        return report(replace(p, best_model=best))
    return mapped


def validation_segments(record: Record, settings: JobSettings
                        ) -> tuple[list[tuple[int, int]], list[tuple[int, int]], dict]:
    """The estimation and validation segments of a record, and its data account.

    Raises
    ------
    DataError
        No segment longer than the largest lag.
    SettingsError
        Correlation lags the validation rows cannot carry.
    """
    space = settings.term_space
    period = int(round(settings.sample_period * 1e9)) or None
    segments = record.segment_info(period, settings.gap_factor)
    bounds, data = segment_report(segments, space.max_lag, record.rejected, record.unpaired)
    if record.spikes:
        data["spike_samples"] = int(record.spikes["samples"])
    if not bounds:
        raise DataError(
            f"no contiguous segment is longer than the largest lag ({space.max_lag}): "
            f"{len(record)} samples in {len(segments.bounds)} segment(s) with "
            f"{segments.gaps} gap(s)" + _decimation_words(record))
    est = val = bounds
    if settings.validation == "holdout":
        est, val = split_segments(bounds, len(record), settings.validation_split,
                                  space.max_lag)
    if settings.validation != "none":
        check_correlation_lags(settings.correlation_lags,
                               sum(b - a - space.max_lag for a, b in val))
    return est, val, data


def _decimation_words(record: Record) -> str:
    """Where a decimated record came from, for an error about its size."""
    doc = record.decimation
    return (f", after decimating by {doc['factor']} ({doc['samples']} samples recorded; "
            "a smaller --decimate keeps more)") if doc else ""


@one_blas_thread()
def _rows(x: np.ndarray, segments: list[tuple[int, int]]) -> np.ndarray:
    """The samples of the segments, one after the other."""
    return np.concatenate([x[a:b] for a, b in segments])


def run_single_job(
    record: Record, settings: JobSettings, *, progress: ProgressFn | None = None,
    progress_every: int = 25, metadata: Mapping[str, Any] | None = None,
) -> JobResult:
    """Identify and validate a record of one output.

    Parameters
    ----------
    record : Record
        The samples, their names, stamps and account
        (:func:`spm_sysid.core.record.load_record`). Gaps and restarts in its
        stamps split it into segments and no regression row crosses one.
    settings : JobSettings
        Term space, GA, criterion, validation and timeline settings; the term
        space takes the record's signal names.
    progress, progress_every : callable, int
        Called with :class:`~spm_sysid.core.progress.Progress` records: checking
        data, every ``progress_every`` generations of the search (and the last),
        certification, refinement, validation.
    metadata : mapping, optional
        Extra entries for the model document's metadata.

    Raises
    ------
    DataError, SettingsError
        Too little usable data, or nothing could be fitted; settings that do not fit
        the data (per-input lags, correlation lags).
    """
    t0 = time.perf_counter()
    report = progress or (lambda p: None)
    report(Progress("checking data", elapsed=0.0))
    settings = settings.for_signals(record.input_names, record.output_name)
    u, y = record.u, record.y
    est, val, data = validation_segments(record, settings)
    point, kept_as_is = _operating_point(settings, u, y, est)
    du, dy = point.centred(u, y) if point is not None else (u, y)
    orders = None
    if settings.orders == "auto":  # the lags and degree from the estimation data
        report(Progress("orders", elapsed=time.perf_counter() - t0))
        settings, orders = choose_orders(record, settings, est, du, dy)
        est, val, data = validation_segments(record, settings)
    if settings.regressors:  # presets take their scales from the estimation data
        settings = settings.with_regressors(_rows(dy, est), _rows(du, est), own_sign_at(point))
        est, val, data = validation_segments(record, settings)
    space = settings.term_space
    problem, ident = _identified((du, dy), est, settings, (point, kept_as_is),
                                 _throttled(report, progress_every), t0, record.fed_back)
    t1 = time.perf_counter()
    model = ident.model
    validation = None
    if settings.validation != "none":
        report(Progress("validation", elapsed=t1 - t0, best_model=lambda: model))
        validation = _validated(model, u, y, settings, val)
    t2 = time.perf_counter()
    seconds = {"search": t1 - t0, "validation": t2 - t1, "total": t2 - t0}
    _record_account(model.metadata, record, (data, est), orders, seconds, metadata)
    times = record.row_seconds(val, space.max_lag) if validation is not None else None
    return JobResult(model=model, report=validation, search=ident.ga, data=data,
                     estimation_samples=problem.n_samples, seconds=seconds,
                     validation_segments=list(val), times=times)


def _identified(signals, est, settings: JobSettings, around, report: ProgressFn, t0: float,
                fed_back: tuple[str, ...] = ()):
    """The problem of ``signals`` (u, y or their deviations) and its identification.

    ``around``: the operating point and why the record was kept as it is (either
    None); the model is returned in the record's units, the point in its metadata.
    ``fed_back``: the inputs that are other outputs (:attr:`Record.fed_back`).
    """
    point, kept_as_is = around
    space = settings.term_space
    if point is not None:  # a model of the record's units may need no constant, one of
        space = replace(space, constant=True)  # the deviations does: a candidate
    problem = Problem.from_signals(*signals, space, est)
    problem.fed_back = tuple(fed_back)
    ident = identify_problem(problem, settings.search, ga=settings.ga,
                             progress=_in_units(report, point), started=t0)
    if point is not None:
        ident.model = in_record_units(ident.model, point)
    if kept_as_is:
        ident.model.metadata["operating_point"] = {"reason": kept_as_is}
    return problem, ident


def _throttled(report: ProgressFn, every: int) -> ProgressFn:
    """``report`` for every ``every``-th generation of the search (and the last), all else."""
    def throttled(p: Progress) -> None:
        if p.phase != "search" or p.step % every == 0 or p.step == p.total:
            report(p)
    return throttled


def _validated(model: NarxModel, u: np.ndarray, y: np.ndarray, settings: JobSettings,
               val: list[tuple[int, int]]):
    """The model validated on its validation segments; its report and monitor reference stored."""
    validation = validate_model(model, u, y, correlation_lags=settings.correlation_lags,
                                segment=settings.validation, segments=val,
                                horizon=settings.horizon or None)
    model.metadata["validation"] = validation.to_dict()
    set_explained_warning(model.metadata)
    store_monitor_reference(model.metadata, validation.residuals, u)
    return validation


def _record_account(meta: dict, record: Record, used: tuple[dict, list], orders: dict | None,
                    seconds: dict, metadata: Mapping[str, Any] | None) -> None:
    """The model's metadata gains what the job used: orders, data, ranges, record, seconds.

    ``used``: the data account and the estimation segments (each signal's range on them).
    """
    data, est = used
    if orders is not None:
        meta["orders"] = orders
    meta["data"] = data
    meta["ranges"] = data_ranges(record.u, record.y, est, record.input_names,
                                 (record.output_name,))
    meta["samples_used"] = data["used_samples"]
    meta.update(record.metadata())
    meta["identify_seconds"] = round(seconds["total"], 4)
    meta.update(metadata or {})

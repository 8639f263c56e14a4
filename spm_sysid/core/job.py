"""One job: a record in, a validated model out, with frozen settings and a typed result.

::

    Record --segments, split--> Problem --identify_problem--> model --validate--> JobResult

The command line, ``batch``, the node's worker process, the ``make run``
pipeline and the benchmarks all call :func:`run_job`. Settings are a frozen
:class:`JobSettings` built once, at the edge, from the settings schema
(:mod:`spm_sysid.core.settings`); the signals' names come with the record
(:mod:`spm_sysid.core.record`). The result is a :class:`JobResult` (model,
validation report, search statistics, data account, timings) with the one
summary formatter, :meth:`JobResult.summary`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .blas import one_blas_thread
from .errors import DataError, SettingsError
from .narx.certify import describe_certificate
from .narx.criteria import get_criterion
from .narx.ga import GAConfig, GAResult
from .narx.identify import identify_problem
from .narx.model import NarxModel
from .narx.problem import Problem
from .narx.segments import describe_data, segment_report
from .narx.terms import TermSpace
from .narx.validation import (
    ValidationReport,
    check_correlation_lags,
    split_segments,
    validate_model,
)
from .online.monitor import store_monitor_reference
from .progress import Progress, ProgressFn
from .record import Record
from .settings import JOB_GROUPS, check, defaults

__all__ = ["JobResult", "JobSettings", "describe_selection", "run_job", "validation_segments",
           "warm_up"]


def warm_up() -> None:
    """Load (or, the first time, compile) the compiled kernels once.

    The node's worker process calls it before it reports ready, so the time of a
    job (and its ``job_timeout``) is the job's own.
    """
    from .narx.evaluator import StructureEvaluator
    from .narx.simulation import free_run_sensitivities

    StructureEvaluator(np.eye(3), np.ones(3)).evaluate(np.eye(3, dtype=bool))
    model = NarxModel(TermSpace(ny=1, nu=1, degree=1), [0, 1], np.array([0.5, 0.1]))
    model.run(np.zeros(6), np.ones(6), horizon=2)
    free_run_sensitivities(model.compiled, model.coefficients, np.zeros((6, 1)), np.ones(6))


_TERM_FIELDS = ("ny", "nu", "degree", "delay", "constant")
_GA_FIELDS = ("population_size", "generations", "crossover_prob", "mutation_prob",
              "spm_fraction", "fitness", "init_terms", "mutation_per_structure", "elitism")


@dataclass(frozen=True)
class JobSettings:
    """Everything a job needs besides the data; build it with :meth:`from_values`.

    Attributes
    ----------
    term_space : TermSpace
    ga : GAConfig
    criterion : str
        A registered criterion name (``aic``, ``bic``, ``pmic2``, ...).
    seed : int or None
        None: a new random seed (the schema's -1).
    validation : str
        ``estimation``, ``holdout`` or ``none``.
    validation_split, correlation_lags, sample_period, gap_factor
        See the settings schema.
    """

    term_space: TermSpace = field(default_factory=TermSpace)
    ga: GAConfig = field(default_factory=GAConfig)
    criterion: str = "aic"
    seed: int | None = None
    validation: str = "estimation"
    validation_split: float = 0.5
    correlation_lags: int = 20
    sample_period: float = 0.0
    gap_factor: float = 1.5
    focus: str = "prediction"
    shortlist: int = 20
    selection: str = "auto"
    max_terms: int = 0
    horizon: int = 0
    certify: bool = False
    certify_time_limit: float = 60.0
    polish: bool = True
    auto_certify_time_limit: float = 10.0

    @classmethod
    def from_values(cls, values: Mapping[str, Any], inputs: tuple[str, ...] = (),
                    output: str = "y") -> JobSettings:
        """Checked settings from a mapping of schema names (others are ignored).

        Missing names take the schema's defaults; ``nu`` and ``delay`` may be one
        value per input. ``inputs``/``output`` name the signals (their number fixes
        the number of inputs). Raises SettingsError (a ValueError) naming the first
        invalid setting.
        """
        v = defaults(JOB_GROUPS)
        v.update({k: values[k] for k in v if k in values and values[k] is not None})
        for name in ("criterion", "seed", "validation", "validation_split",
                     "correlation_lags", "sample_period", "gap_factor", "focus", "shortlist",
                     "selection", "max_terms", "horizon", "certify", "certify_time_limit",
                     "polish", "auto_certify_time_limit"):
            v[name] = check(name, v[name])
        criterion = v["criterion"].lower()
        try:
            get_criterion(criterion)
        except (KeyError, ValueError) as exc:
            raise SettingsError(str(exc).strip("'\"")) from None
        return cls(
            term_space=TermSpace(**{k: v[k] for k in _TERM_FIELDS}, inputs=tuple(inputs),
                                 output=output),
            ga=GAConfig(**{k: v[k] for k in _GA_FIELDS}),
            criterion=criterion,
            seed=None if v["seed"] < 0 else v["seed"],
            validation=v["validation"],
            validation_split=v["validation_split"],
            correlation_lags=v["correlation_lags"],
            sample_period=v["sample_period"],
            gap_factor=v["gap_factor"],
            focus=v["focus"],
            shortlist=v["shortlist"],
            selection=v["selection"],
            max_terms=v["max_terms"],
            horizon=v["horizon"],
            certify=v["certify"],
            certify_time_limit=v["certify_time_limit"],
            polish=v["polish"],
            auto_certify_time_limit=v["auto_certify_time_limit"],
        )

    def for_signals(self, inputs: tuple[str, ...], output: str) -> JobSettings:
        """These settings with the term space naming a record's signals.

        Raises
        ------
        SettingsError
            Per-input settings (``nu``, ``delay``) that do not fit the number of
            inputs.
        """
        from dataclasses import replace

        if (tuple(inputs), output) == (self.term_space.inputs, self.term_space.output):
            return self
        try:
            space = replace(self.term_space, inputs=tuple(inputs), output=output)
        except ValueError as exc:
            raise SettingsError(str(exc)) from None
        return replace(self, term_space=space)


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
        Samples, segments, gaps ... (:func:`spm_sysid.core.narx.segments.segment_report`).
    estimation_samples : int
        Samples the fit used.
    seconds : dict
        ``search``, ``validation`` and ``total`` wall-clock seconds.
    """

    model: NarxModel
    report: ValidationReport | None
    search: GAResult
    data: dict
    estimation_samples: int
    seconds: dict = field(default_factory=dict)

    @property
    def residuals(self) -> np.ndarray:
        """One-step residuals of the validation rows (empty without validation)."""
        return np.empty(0) if self.report is None else self.report.residuals

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
        cert = describe_certificate(m.metadata.get("certificate"))
        pol = m.metadata.get("polish") or {}
        if pol.get("value") is not None and pol["value"] < pol["ga_value"]:
            cert = (f"the polish after the GA improved its best from {pol['ga_value']:.2f} "
                    f"({pol['steps']} step(s))" + (f", {cert}" if cert else ""))
        warnings = m.metadata.get("warnings") or []
        selected = describe_selection(m.metadata.get("selection"))
        if style == "line":
            text = (f"{m.equation()} | {crit} {value:.2f}, {len(m.term_indices)} terms, "
                    f"one-step MSE {m.mse:.4e}, {describe_data(self.data)}")
            if selected:
                text += f", {selected}"
            if cert:
                text += f", {cert}"
            if self.report is not None:
                r = self.report
                o, f = r.one_step_metrics, r.free_run_metrics
                failed = [t.name for t in r.tests if not t.passed]
                free = (f"free-run DIVERGED at sample {f['diverged_at']}"
                        if f.get("diverged_at") is not None
                        else f"free-run fit {f['fit_percent']:.1f} %")
                tests = ("correlation tests not computed" if r.tests_skipped else
                         "correlation tests " + ("all inside the band" if not failed
                                                 else "outside the band: " + ", ".join(failed)))
                text += (f" ({r.segment} validation: one-step fit {o['fit_percent']:.1f} %, "
                         f"{free}, {tests})")
            if warnings:
                text += "; WARNING: " + "; WARNING: ".join(warnings)
            return text + f", {self.seconds.get('total', 0.0):.2f} s"
        lines = [m.equation(),
                 f"criterion {crit} = {value:.2f}, {len(m.term_indices)} terms, one-step MSE "
                 f"{m.mse:.4e}, {m.n_samples} samples, "
                 f"{self.seconds.get('search', self.search.elapsed):.2f} s "
                 f"({self.search.evaluations} structures fitted, cache hit rate "
                 f"{self.search.cache_hit_rate:.0%})"]
        if selected:
            lines.append(selected)
        if cert:
            lines.append(cert)
        lines.append(m.coefficient_table())
        lines += [f"warning: {w}" for w in warnings]
        if self.report is not None:
            lines.append(self.report.summary())
        return "\n".join(lines)


def describe_selection(doc: dict | None) -> str:
    """How the structure was chosen, in a few words ('' when the document has nothing)."""
    if not doc:
        return ""
    if doc.get("method") == "validated":
        held = doc.get("held_out_mse")
        text = (f"selected by its {doc['what']} error on {doc['folds']} held-out blocks "
                + (f"(MSE {held:.4g})" if held is not None else ""))
        removed = doc.get("removed_by_guard")
        if removed:
            text += (f"; the stability guard removed {removed} structure(s) whose simulation "
                     "left the output's range off the estimation data")
        return text
    return f"selected by the criterion on the estimation data ({doc.get('note', '')})"


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
    if not bounds:
        raise DataError(
            f"no contiguous segment is longer than the largest lag ({space.max_lag}): "
            f"{len(record)} samples in {len(segments.bounds)} segment(s) with "
            f"{segments.gaps} gap(s)")
    est = val = bounds
    if settings.validation == "holdout":
        est, val = split_segments(bounds, len(record), settings.validation_split,
                                  space.max_lag)
    if settings.validation != "none":
        check_correlation_lags(settings.correlation_lags,
                               sum(b - a - space.max_lag for a, b in val))
    return est, val, data


@one_blas_thread()
def run_job(
    record: Record,
    settings: JobSettings,
    *,
    progress: ProgressFn | None = None,
    progress_every: int = 25,
    metadata: Mapping[str, Any] | None = None,
) -> JobResult:
    """Identify and validate a record.

    Parameters
    ----------
    record : Record
        The samples, their names, stamps and account
        (:func:`spm_sysid.core.record.load_record`, or
        :meth:`~spm_sysid.core.record.Record.from_samples`). Gaps and restarts in
        its stamps split it into segments (``settings.sample_period``,
        ``settings.gap_factor``) and no regression row crosses one.
    settings : JobSettings
        Term space, GA, criterion, validation and timeline settings; the term
        space takes the record's signal names.
    progress : callable, optional
        Called with :class:`~spm_sysid.core.progress.Progress` records: checking
        data, every ``progress_every`` generations of the search (and the last),
        certification, refinement, validation.
    progress_every : int
        Generations between search reports.
    metadata : mapping, optional
        Extra entries for the model document's metadata.

    Returns
    -------
    JobResult
        Or, for a record of several outputs, a
        :class:`~spm_sysid.core.mimo_job.MimoJobResult` (one coupled model).

    Raises
    ------
    DataError
        Too little usable data, or nothing could be fitted.
    SettingsError
        Settings that do not fit the data (per-input lags, correlation lags).
    """
    if record.n_outputs > 1:  # one coupled model of several outputs
        from .mimo_job import run_mimo_job

        return run_mimo_job(record, settings, progress=progress,
                            progress_every=progress_every, metadata=metadata)
    t0 = time.perf_counter()
    report = progress or (lambda p: None)
    report(Progress("checking data", elapsed=0.0))
    settings = settings.for_signals(record.input_names, record.output_name)
    space = settings.term_space
    u, y = record.u, record.y
    est, val, data = validation_segments(record, settings)

    def throttled(p: Progress) -> None:
        if p.phase != "search" or p.step % progress_every == 0 or p.step == p.total:
            report(p)

    problem = Problem.from_signals(u, y, space, est)
    ident = identify_problem(problem, criterion=settings.criterion, ga=settings.ga,
                             seed=settings.seed, focus=settings.focus,
                             shortlist=settings.shortlist, selection=settings.selection,
                             max_terms=settings.max_terms,
                             certify_time_limit=(settings.certify_time_limit if settings.certify
                                                 else None),
                             polish=settings.polish,
                             auto_certify_time_limit=settings.auto_certify_time_limit,
                             progress=throttled, started=t0)
    t1 = time.perf_counter()
    model = ident.model
    validation = None
    if settings.validation != "none":
        report(Progress("validation", elapsed=t1 - t0))
        validation = validate_model(model, u, y, correlation_lags=settings.correlation_lags,
                                    segment=settings.validation, segments=val,
                                    horizon=settings.horizon or None)
        model.metadata["validation"] = validation.to_dict()
        store_monitor_reference(model.metadata, validation.residuals, u)
    t2 = time.perf_counter()
    seconds = {"search": t1 - t0, "validation": t2 - t1, "total": t2 - t0}
    model.metadata["data"] = data
    model.metadata["samples_used"] = data["used_samples"]
    model.metadata.update(record.metadata())
    model.metadata["identify_seconds"] = round(seconds["total"], 4)
    model.metadata.update(metadata or {})
    return JobResult(model=model, report=validation, search=ident.ga, data=data,
                     estimation_samples=problem.n_samples, seconds=seconds)

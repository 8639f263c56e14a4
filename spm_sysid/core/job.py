"""One job: identify and validate, with frozen settings and a typed result.

The command line, the node's worker process, the ``make run`` pipeline and the
benchmarks all call :func:`run_job`. Settings are a frozen
:class:`JobSettings` built once, at the edge, from the settings schema
(:mod:`spm_sysid.core.settings`); the result is a :class:`JobResult` (model,
validation report, search statistics, data account, timings) with the one
summary formatter, :meth:`JobResult.summary`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import DataError, SettingsError
from .narx.criteria import get_criterion
from .narx.ga import GAConfig, GAResult
from .narx.identify import identify
from .narx.model import NarxModel
from .narx.segments import SegmentInfo, describe_data, find_segments, segment_report
from .narx.terms import TermSpace
from .narx.validation import (
    ValidationReport,
    check_correlation_lags,
    split_segments,
    validate_model,
)
from .settings import JOB_GROUPS, check, defaults

__all__ = ["JobResult", "JobSettings", "describe_certificate", "run_job", "warm_up"]


def describe_certificate(doc: dict | None) -> str:
    """The certificate of a model document in a few words ('' when none)."""
    if not doc:
        return ""
    if doc["status"] == "optimal":
        text = (f"certified optimal over all structures ({doc['nodes']} nodes, "
                f"{doc['seconds']:.2f} s)")
    elif doc["status"] == "limit":
        text = (f"NOT certified ({doc['reason']}): lower bound {doc['lower_bound']:.2f}, "
                f"gap {doc['gap']:.2f}")
    else:
        return f"not certifiable: {doc['reason']}"
    if doc.get("ga_value") is not None and doc["value"] < doc["ga_value"]:
        text += f"; the search improved on the GA's {doc['ga_value']:.2f}"
    return text


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
    horizon: int = 0
    certify: bool = False
    certify_time_limit: float = 60.0

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
                     "horizon", "certify", "certify_time_limit"):
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
            horizon=v["horizon"],
            certify=v["certify"],
            certify_time_limit=v["certify_time_limit"],
        )

    def values(self) -> dict[str, Any]:
        """Back to schema names (for documents and logs)."""
        out = {**self.term_space.to_dict(), **self.ga.to_dict()}
        out.update(criterion=self.criterion, seed=-1 if self.seed is None else self.seed,
                   validation=self.validation, validation_split=self.validation_split,
                   correlation_lags=self.correlation_lags, sample_period=self.sample_period,
                   gap_factor=self.gap_factor, focus=self.focus, shortlist=self.shortlist,
                   horizon=self.horizon, certify=self.certify,
                   certify_time_limit=self.certify_time_limit)
        return out


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
        command line's block (equation, criterion, data, validation).
        """
        m, crit = self.model, self.model.criterion.upper()
        value = m.criterion_value
        if m.metadata.get("focus") == "simulation":
            crit += " (simulation)"
        cert = describe_certificate(m.metadata.get("certificate"))
        if style == "line":
            text = (f"{m.equation()} | {crit} {value:.2f}, {len(m.term_indices)} terms, "
                    f"one-step MSE {m.mse:.4e}, {describe_data(self.data)}")
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
            return text + f", {self.seconds.get('total', 0.0):.2f} s"
        lines = [m.equation(),
                 f"criterion {crit} = {value:.2f}, {len(m.term_indices)} terms, one-step MSE "
                 f"{m.mse:.4e}, {m.n_samples} samples, "
                 f"{self.seconds.get('search', self.search.elapsed):.2f} s "
                 f"({self.search.evaluations} structures fitted, cache hit rate "
                 f"{self.search.cache_hit_rate:.0%})"]
        if cert:
            lines.append(cert)
        if self.report is not None:
            lines.append(self.report.summary())
        return "\n".join(lines)


def run_job(
    u: np.ndarray,
    y: np.ndarray,
    settings: JobSettings,
    *,
    stamps_ns: np.ndarray | None = None,
    segments: SegmentInfo | None = None,
    rejected: int = 0,
    unpaired: int = 0,
    progress: Callable[[int, float, int], None] | None = None,
    progress_every: int = 25,
    metadata: Mapping[str, Any] | None = None,
) -> JobResult:
    """Identify and validate.

    Parameters
    ----------
    u, y : ndarray, shape (n,)
        The record, oldest first.
    settings : JobSettings
        Term space, GA, criterion, validation and timeline settings.
    stamps_ns : ndarray of int, optional
        Sample stamps: gaps and restarts in them split the record into segments
        (:func:`spm_sysid.core.narx.segments.find_segments`) and no regression
        row crosses one. Without stamps (and ``segments``) the record is one
        contiguous segment.
    segments : SegmentInfo, optional
        Segments already found (instead of ``stamps_ns``).
    rejected, unpaired : int
        Samples dropped before (NaN/inf, without a partner), for the account.
    progress : callable, optional
        ``progress(generation, best, evaluations)`` every ``progress_every``
        generations and at the last.
    progress_every : int
        Generations between progress calls.
    metadata : mapping, optional
        Extra entries for the model document's metadata.

    Raises
    ------
    DataError
        Too little usable data, or nothing could be fitted.
    """
    t0 = time.perf_counter()
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    space = settings.term_space
    if segments is None:
        if stamps_ns is None:
            segments = SegmentInfo([(0, len(y))] if len(y) else [])
        else:
            period = int(round(settings.sample_period * 1e9)) or None
            segments = find_segments(stamps_ns, period, settings.gap_factor)
    bounds, data = segment_report(segments, space.max_lag, rejected, unpaired)
    if not bounds:
        raise DataError(
            f"no contiguous segment is longer than the largest lag ({space.max_lag}): "
            f"{len(y)} samples in {len(segments.bounds)} segment(s) with {segments.gaps} gap(s)")
    whole = bounds == [(0, len(y))]
    est = val = None if whole else bounds
    if settings.validation == "holdout":
        est, val = split_segments(bounds, len(y), settings.validation_split, space.max_lag)
    if settings.validation != "none":
        check_correlation_lags(settings.correlation_lags,
                               sum(b - a - space.max_lag for a, b in (val or [(0, len(y))])))

    def callback(stats):
        if progress is not None and (stats.generation % progress_every == 0
                                     or stats.generation == settings.ga.generations):
            progress(stats.generation, stats.best, stats.evaluations)

    ident = identify(u=u, y=y, term_space=space, criterion=settings.criterion,
                     ga=settings.ga, seed=settings.seed, callback=callback, segments=est,
                     focus=settings.focus, shortlist=settings.shortlist,
                     certify_time_limit=(settings.certify_time_limit if settings.certify
                                         else None))
    t1 = time.perf_counter()
    model = ident.model
    report = None
    if settings.validation != "none":
        report = validate_model(model, u, y, max_lag=settings.correlation_lags,
                                segment=settings.validation, segments=val,
                                horizon=settings.horizon or None)
        model.metadata["validation"] = report.to_dict()
    t2 = time.perf_counter()
    seconds = {"search": t1 - t0, "validation": t2 - t1, "total": t2 - t0}
    model.metadata["data"] = data
    model.metadata["samples_used"] = data["used_samples"]
    if stamps_ns is not None and len(stamps_ns):
        model.metadata["first_stamp_ns"] = int(stamps_ns[0])
        model.metadata["last_stamp_ns"] = int(stamps_ns[-1])
    model.metadata["identify_seconds"] = round(seconds["total"], 4)
    model.metadata.update(metadata or {})
    used = sum(b - a for a, b in (est or [(0, len(y))]))
    return JobResult(model=model, report=report, search=ident.ga, data=data,
                     estimation_samples=used, seconds=seconds)


"""Validating a model on a data segment: predictions, error metrics, correlation tests.

Always both: one-step-ahead prediction (measured outputs as regressors, what
least squares optimises) and free-run simulation (the model's own outputs fed
back, what a simulator or controller would see). On the robot-arm data the
paper's eq. (1) predicts one step ahead very well and simulates poorly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DataError, SettingsError
from ..model.narx import NarxModel
from ..model.segments import rows_segments
from ..model.uncertainty import Band, output_band
from .correlation import CorrelationTest, correlation_tests

__all__ = ["ValidationReport", "check_correlation_lags", "describe_metrics", "metrics",
           "split_segments", "validate_model"]


def metrics(y: np.ndarray, yhat: np.ndarray, diverged_at: int | None = None
            ) -> dict[str, float | int | None]:
    """Error metrics of a prediction.

    ``fit_percent`` is the normalised-RMSE fit MATLAB's ``compare`` reports:
    ``100 * (1 - ||y - yhat|| / ||y - mean(y)||)``; 100 is perfect, and it can be
    negative (worse than the mean); NaN (``null`` in documents) when the output does
    not vary beyond the rounding of its mean (a fit has no meaning there). A run that
    diverged (``diverged_at``, a sample index, or any non-finite prediction) has no
    error metrics: they are NaN and ``diverged_at`` says where it left the range
    (never ``inf``).
    """
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    e = y - yhat
    if diverged_at is not None or not np.all(np.isfinite(e)):
        nan = float("nan")
        if diverged_at is None:
            diverged_at = int(np.flatnonzero(~np.isfinite(e))[0])
        return {"mse": nan, "rmse": nan, "max_abs": nan, "mean_abs": nan,
                "fit_percent": nan, "diverged_at": int(diverged_at)}
    spread = np.linalg.norm(y - y.mean())
    # an output that does not vary (beyond rounding of its mean) has no fit: not -7e16 %
    level = np.linalg.norm(y)
    fit = (100.0 * (1.0 - np.linalg.norm(e) / spread) if spread > 1e-12 * level and spread > 0
           else float("nan"))
    mse = float(np.mean(e**2))
    return {
        "mse": mse,
        "rmse": float(np.sqrt(mse)),
        "max_abs": float(np.max(np.abs(e))),
        "mean_abs": float(np.mean(np.abs(e))),
        "fit_percent": float(fit),
        "diverged_at": None,
    }


def describe_metrics(label: str, m: dict) -> str:
    """One line of a metrics dictionary for people."""
    if m.get("diverged_at") is not None:
        return (f"  {label}: DIVERGED at sample {m['diverged_at']} (left the measured "
                f"output's range; no error metrics)")
    fit = m.get("fit_percent")
    fit = (f"fit {fit:.2f} %" if fit is not None and np.isfinite(fit) else
           "no fit % (the output does not vary here)")
    return (f"  {label}: MSE {m['mse']:.4e}, RMSE {m['rmse']:.4g}, max |e| {m['max_abs']:.4g}, "
            f"mean |e| {m['mean_abs']:.4g}, {fit}")


@dataclass
class ValidationReport:
    """Everything validation computed on one segment (rows t = max_lag..n-1).

    ``tests`` is empty when the correlation tests were not computed
    (``tests_skipped`` says why: a diverged simulation or non-finite residuals).
    """

    measured: np.ndarray
    one_step: np.ndarray
    free_run: np.ndarray
    one_step_metrics: dict
    free_run_metrics: dict
    tests: list[CorrelationTest]
    segment: str = "estimation"
    n_samples: int = 0
    horizon: int | None = None
    k_step: np.ndarray | None = None
    k_step_metrics: dict | None = None
    tests_skipped: str | None = None
    one_step_band: Band | None = None
    free_run_band: Band | None = None
    errors_from: int = 0
    scored: np.ndarray | None = None

    def score(self, predicted: np.ndarray, diverged_at: int | None = None) -> dict:
        """:func:`metrics` of a prediction of ``measured`` over the rows scored.

        ``scored`` (None: every row) leaves out each segment's first
        ``errors_from`` samples (:func:`validate_model`).
        """
        keep = slice(None) if self.scored is None else self.scored
        return metrics(self.measured[keep], np.asarray(predicted)[keep], diverged_at)

    @property
    def residuals(self) -> np.ndarray:
        """One-step residuals."""
        return self.measured - self.one_step

    @property
    def diverged_at(self) -> int | None:
        """Sample where the free-run simulation diverged, or None."""
        return self.free_run_metrics.get("diverged_at")

    @property
    def passed(self) -> bool:
        """No divergence, correlation tests computed and all inside the band."""
        return (self.diverged_at is None and self.tests_skipped is None
                and all(t.passed for t in self.tests))

    def test(self, name: str) -> CorrelationTest:
        """One correlation test by name (``ee``, ``ue``, ``e_eu``, ``u2_e``, ``u2_e2``)."""
        return next(t for t in self.tests if t.name == name)

    def to_dict(self) -> dict:
        """JSON-ready summary (no arrays; NaN as null)."""
        out = {
            "segment": self.segment,
            "n_samples": self.n_samples,
            "errors_from": self.errors_from,
            "one_step": _finite(self.one_step_metrics),
            "free_run": _finite(self.free_run_metrics),
            "diverged_at": self.diverged_at,
            "correlation_tests": [t.to_dict() for t in self.tests],
        }
        if self.k_step_metrics is not None:
            out["k_step"] = {"horizon": self.horizon, **_finite(self.k_step_metrics)}
        if self.tests_skipped:
            out["correlation_tests_skipped"] = self.tests_skipped
        for key, band in (("one_step_band", self.one_step_band),
                          ("free_run_band", self.free_run_band)):
            if band is not None:
                out[key] = _finite({"level": band.level, "mean_width": band.mean_width,
                                    "draws": band.draws, "diverged_fraction": band.diverged})
        return out

    def summary(self) -> str:
        """A few lines for people."""
        start = (f"; errors from sample {self.errors_from} of each segment"
                 if self.errors_from else "")
        lines = [f"validation on {self.segment} data ({self.n_samples} samples{start}):",
                 describe_metrics("one-step", self.one_step_metrics)]
        if self.k_step_metrics is not None:
            lines.append(describe_metrics(f"{self.horizon}-step", self.k_step_metrics))
        lines.append(describe_metrics("free-run", self.free_run_metrics))
        for label, band in (("one-step", self.one_step_band), ("free-run", self.free_run_band)):
            if band is not None:
                lines.append(f"  {label} {band.level:.0%} band from the coefficients' "
                             f"uncertainty: mean width {band.mean_width:.4g}"
                             + (f"; {band.diverged:.0%} of {band.draws} draws diverged"
                                if band.diverged else ""))
        if self.tests_skipped:
            lines.append(f"  correlation tests: not computed ({self.tests_skipped})")
            return "\n".join(lines)
        lines.append(f"  correlation tests (95 % band ±{self.tests[0].band:.4f}):")
        for t in self.tests:
            state = "OK  " if t.passed else "WARN"
            lines.append(f"    {state} {t.name:<6} {t.fraction_inside:6.1%} of lags inside, "
                         f"worst at lag {t.worst_lag}")
        return "\n".join(lines)


def _finite(d: dict) -> dict:
    return {k: (v if v is None or isinstance(v, int) or np.isfinite(v) else None)
            for k, v in d.items()}


def split_segments(bounds: list[tuple[int, int]], n: int, fraction: float, max_lag: int
                   ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Split segments at ``round(fraction * n)`` into estimation and validation parts.

    The estimation part keeps what lies before the cut; the validation part what
    lies after it, plus the ``max_lag`` samples before the cut as initial
    conditions where they belong to the same segment (so its predictions start
    right after the estimation data ends).
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"split fraction must be in (0, 1), got {fraction}")
    cut = int(round(fraction * n))
    est = [(a, min(b, cut)) for a, b in bounds if a < cut]
    val = [(max(a, cut - max_lag), b) for a, b in bounds if b > cut]
    est = [(a, b) for a, b in est if b - a > max_lag]
    val = [(a, b) for a, b in val if b - a > max_lag]
    if not est or not val:
        raise DataError(f"cannot split {n} samples at {fraction:g}: a part would have no "
                        "segment longer than the largest lag")
    return est, val


def check_correlation_lags(lags: int, rows: int) -> None:
    """Raise SettingsError unless 1 <= ``lags`` < ``rows`` (the validation rows).

    With no more rows than the default 20 lags, the message says that the data
    are too short (the cure), not only which lags would fit.
    """
    if rows < 2:
        raise SettingsError(f"too few samples to validate: {rows} validation row(s), the "
                            "correlation tests need at least 2 (more data, or validation: "
                            "none)")
    if not 1 <= lags < rows:
        short = (f"too few samples to validate with correlation_lags {lags}: {rows} "
                 f"validation rows; record more data (at least {lags + 1} rows), or set "
                 f"correlation_lags to at most {rows - 1}")
        raise SettingsError(short if lags >= 1 and rows <= 20 else
                            f"correlation_lags must be between 1 and {rows - 1} for {rows} "
                            f"validation rows, got {lags}")


def validate_model(
    model: NarxModel, u: np.ndarray, y: np.ndarray, *, correlation_lags: int = 20,
    segment: str = "estimation", segments: list[tuple[int, int]] | None = None,
    horizon: int | None = None, bands: bool = True, errors_from: int = 0,
) -> ValidationReport:
    """Validate ``model`` on u, y (one-step, free-run, correlation tests).

    Parameters
    ----------
    model : NarxModel
        The model to validate.
    u, y : ndarray, shape (n,)
        The segment; its first ``max_lag`` samples serve as initial conditions.
    correlation_lags, segment : int, str
        Largest lag of the correlation tests; the reports' label (``"holdout"``...).
    segments : list of (start, stop), optional
        Contiguous parts of the record (see :mod:`spm_sysid.core.model.segments`):
        predictions never cross from one to the next, and each is simulated from
        its own initial conditions. The correlation tests run on the residuals of
        all segments, concatenated.
    horizon : int, optional
        Also report k-step-ahead prediction for this k (> 1).
    bands : bool
        With a model that carries coefficient uncertainty, 95 % bands of its
        one-step and free-run outputs (:func:`~spm_sysid.core.model.uncertainty.output_band`).
    errors_from : int
        The error metrics leave out each segment's first ``errors_from`` samples
        (the benchmarks' convention: the first 50 samples of a test record may
        initialise the simulation, which still starts from the first ``max_lag``);
        the arrays and the correlation tests keep every row.
    """
    u, y, segments = _checked_record(model, u, y, segments, correlation_lags)
    lag0 = model.term_space.max_lag
    scored = _scored_rows(segments, lag0, errors_from)
    report = ValidationReport(measured=model.measured(y, segments), one_step=np.empty(0),
                              free_run=np.empty(0), one_step_metrics={}, free_run_metrics={},
                              tests=[], segment=segment, errors_from=int(errors_from),
                              scored=scored, n_samples=sum(b - a for a, b in segments))
    measured = report.measured
    one_step = model.predict(u, y, segments)
    free_run, diverged = model.run(u, y, None, segments)
    k_step = k_metrics = None
    if horizon is not None and horizon > 1:
        k_step, k_div = model.run(u, y, horizon, segments)
        k_metrics = report.score(k_step, k_div)
    free_metrics = report.score(free_run, diverged)
    tests, skipped = _tests(measured - one_step, free_metrics, u, segments, lag0,
                            correlation_lags)
    if bands and model.uncertainty is not None:
        report.one_step_band = output_band(model, u, y, horizon=1, segments=segments)
        report.free_run_band = output_band(model, u, y, horizon=None, segments=segments)
    report.one_step, report.free_run = one_step, free_run
    report.one_step_metrics, report.free_run_metrics = report.score(one_step), free_metrics
    report.tests, report.tests_skipped = tests, skipped
    report.horizon = horizon if k_step is not None else None
    report.k_step, report.k_step_metrics = k_step, k_metrics
    return report


def _tests(residuals: np.ndarray, free_metrics: dict, u: np.ndarray, segments, lag0: int,
           correlation_lags: int) -> tuple[list[CorrelationTest], str | None]:
    """The correlation tests of the residuals, or why they were not computed."""
    if free_metrics["diverged_at"] is not None:
        return [], (f"the free-run simulation diverged at sample "
                    f"{free_metrics['diverged_at']}: the model does not describe the system")
    if not np.all(np.isfinite(residuals)):
        return [], "the one-step residuals are not finite"
    # the correlation tests use the first input (several inputs: docs/method.md)
    u_rows = np.concatenate([u[a + lag0:b, 0] for a, b in segments])
    return correlation_tests(residuals, u_rows, correlation_lags), None


def _scored_rows(segments: list[tuple[int, int]], lag0: int, errors_from: int
                 ) -> np.ndarray | None:
    """The rows whose errors count: each segment's samples from ``errors_from`` on.

    None: every row (``errors_from`` within the initial conditions).
    """
    errors_from = int(errors_from)
    if errors_from < 0:
        raise SettingsError(f"errors_from must be 0 or more, got {errors_from}")
    if errors_from <= lag0:
        return None
    keep = np.concatenate([np.arange(lag0, b - a) >= errors_from for a, b in segments])
    if not keep.any():
        longest = max(b - a for a, b in segments)
        raise DataError(f"errors from sample {errors_from} leave no sample to score: the "
                        f"longest segment has {longest} samples")
    return keep


def _checked_record(model: NarxModel, u: np.ndarray, y: np.ndarray,
                    segments: list[tuple[int, int]] | None,
                    correlation_lags: int) -> tuple[np.ndarray, np.ndarray, list]:
    """Inputs (n, m), output and row segments, once they hold enough rows; else a DataError."""
    try:
        u = model.term_space.inputs_2d(u)
    except ValueError as exc:
        raise DataError(str(exc)) from None
    y = np.asarray(y, dtype=float)
    lag0 = model.term_space.max_lag
    if len(y) != len(u):
        raise DataError(f"u and y differ in length: {len(u)} and {len(y)}")
    segments = rows_segments(segments, len(y), lag0)
    rows = sum(b - a - lag0 for a, b in segments)
    if rows < max(3, correlation_lags + 1):
        raise DataError(f"too few samples to validate: {rows} regression rows (need at "
                        f"least {max(3, correlation_lags + 1)})")
    return u, y, segments

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
from .correlation import CorrelationTest, correlation_tests
from .model import NarxModel

__all__ = ["ValidationReport", "metrics", "split_data", "split_segments", "validate_model",
           "check_correlation_lags"]


def metrics(y: np.ndarray, yhat: np.ndarray) -> dict[str, float]:
    """Error metrics of a prediction.

    ``fit_percent`` is the normalised-RMSE fit MATLAB's ``compare`` reports:
    ``100 * (1 - ||y - yhat|| / ||y - mean(y)||)``; 100 is perfect, and it can be
    negative (worse than the mean). Non-finite predictions (a diverging
    simulation) give infinite errors and a fit of -inf.
    """
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    e = y - yhat
    if not np.all(np.isfinite(e)):
        inf = float("inf")
        return {"mse": inf, "rmse": inf, "max_abs": inf, "mean_abs": inf, "fit_percent": -inf}
    spread = np.linalg.norm(y - y.mean())
    fit = 100.0 * (1.0 - np.linalg.norm(e) / spread) if spread > 0 else float("nan")
    mse = float(np.mean(e**2))
    return {
        "mse": mse,
        "rmse": float(np.sqrt(mse)),
        "max_abs": float(np.max(np.abs(e))),
        "mean_abs": float(np.mean(np.abs(e))),
        "fit_percent": float(fit),
    }


def split_data(
    u: np.ndarray, y: np.ndarray, fraction: float, max_lag: int
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Split into an estimation head and a validation tail.

    The tail keeps the ``max_lag`` samples before it as initial conditions, so
    its predictions start right after the estimation data ends.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"split fraction must be in (0, 1), got {fraction}")
    n = len(y)
    cut = int(round(fraction * n))
    if cut <= max_lag or n - cut < 2:
        raise DataError(f"cannot split {n} samples at {fraction:g}: a part would be too short")
    return (u[:cut], y[:cut]), (u[cut - max_lag:], y[cut - max_lag:])


@dataclass
class ValidationReport:
    """Everything validation computed on one segment (rows t = max_lag..n-1)."""

    measured: np.ndarray
    one_step: np.ndarray
    free_run: np.ndarray
    one_step_metrics: dict[str, float]
    free_run_metrics: dict[str, float]
    tests: list[CorrelationTest]
    segment: str = "estimation"
    n_samples: int = 0

    @property
    def residuals(self) -> np.ndarray:
        """One-step residuals."""
        return self.measured - self.one_step

    def test(self, name: str) -> CorrelationTest:
        """One correlation test by name (``ee``, ``ue``, ``e_eu``, ``u2_e``, ``u2_e2``)."""
        return next(t for t in self.tests if t.name == name)

    def to_dict(self) -> dict:
        """JSON-ready summary (no arrays)."""
        return {
            "segment": self.segment,
            "n_samples": self.n_samples,
            "one_step": _finite(self.one_step_metrics),
            "free_run": _finite(self.free_run_metrics),
            "correlation_tests": [t.to_dict() for t in self.tests],
        }

    def summary(self) -> str:
        """A few lines for people."""
        o, f = self.one_step_metrics, self.free_run_metrics
        lines = [
            f"validation on {self.segment} data ({self.n_samples} samples):",
            f"  one-step: MSE {o['mse']:.4e}, max |e| {o['max_abs']:.4g}, "
            f"mean |e| {o['mean_abs']:.4g}, fit {o['fit_percent']:.2f} %",
            f"  free-run: MSE {f['mse']:.4e}, max |e| {f['max_abs']:.4g}, "
            f"mean |e| {f['mean_abs']:.4g}, fit {f['fit_percent']:.2f} %",
            f"  correlation tests (95 % band ±{self.tests[0].band:.4f}):",
        ]
        for t in self.tests:
            state = "OK  " if t.passed else "WARN"
            lines.append(f"    {state} {t.name:<6} {t.fraction_inside:6.1%} of lags inside, "
                         f"worst at lag {t.worst_lag}")
        return "\n".join(lines)


def _finite(d: dict[str, float]) -> dict[str, float | None]:
    return {k: (v if np.isfinite(v) else None) for k, v in d.items()}


def split_segments(bounds: list[tuple[int, int]], n: int, fraction: float, max_lag: int
                   ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Split segments at ``round(fraction * n)`` like :func:`split_data`.

    The estimation part keeps what lies before the cut; the validation part what
    lies after it, plus the ``max_lag`` samples before the cut as initial
    conditions where they belong to the same segment.
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
    """Raise SettingsError unless 1 <= ``lags`` < ``rows`` (the validation rows)."""
    if not 1 <= lags < rows:
        raise SettingsError(f"correlation_lags must be between 1 and {rows - 1} for {rows} "
                            f"validation rows, got {lags}")


def validate_model(
    model: NarxModel, u: np.ndarray, y: np.ndarray, *, max_lag: int = 20,
    segment: str = "estimation", segments: list[tuple[int, int]] | None = None,
) -> ValidationReport:
    """Validate ``model`` on u, y (one-step, free-run, correlation tests).

    Parameters
    ----------
    model : NarxModel
        The model to validate.
    u, y : ndarray, shape (n,)
        The segment; its first ``model.term_space.max_lag`` samples serve as
        initial conditions.
    max_lag : int
        Largest lag of the correlation tests.
    segment : str
        Label for reports (``"estimation"`` or ``"holdout"``).
    segments : list of (start, stop), optional
        Contiguous parts of the record (see :mod:`spm_sysid.core.narx.segments`):
        predictions never cross from one to the next, and each is simulated from
        its own initial conditions. The correlation tests run on the residuals of
        all segments, concatenated.
    """
    try:
        u = model.term_space.inputs_2d(u)
    except ValueError as exc:
        raise DataError(str(exc)) from None
    y = np.asarray(y, dtype=float)
    lag0 = model.term_space.max_lag
    if len(y) != len(u):
        raise DataError(f"u and y differ in length: {len(u)} and {len(y)}")
    if segments is not None:
        segments = [(a, b) for a, b in segments if b - a > lag0]
    rows = len(y) - lag0 if segments is None else sum(b - a - lag0 for a, b in segments)
    if rows < max(3, max_lag + 1):
        raise DataError(f"too few samples to validate: {rows} regression rows (need at "
                        f"least {max(3, max_lag + 1)})")
    _, measured = model.term_space.regression(u, y, segments)
    one_step = model.predict(u, y, segments)
    free_run = model.simulate_segments(u, y, segments)
    residuals = measured - one_step
    # the correlation tests use the first input (several inputs: docs/method.md)
    u_rows = u[lag0:, 0] if segments is None else np.concatenate(
        [u[a + lag0:b, 0] for a, b in segments])
    return ValidationReport(
        measured=measured,
        one_step=one_step,
        free_run=free_run,
        one_step_metrics=metrics(measured, one_step),
        free_run_metrics=metrics(measured, free_run),
        tests=correlation_tests(residuals, u_rows, max_lag),
        segment=segment,
        n_samples=len(y) if segments is None else sum(b - a for a, b in segments),
    )

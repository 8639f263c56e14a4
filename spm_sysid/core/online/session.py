"""One model on a live stream: prediction, monitor and tracker fed sample by sample.

:class:`OnlineSession` is what the node holds for its current model. Each
paired sample (stamp, inputs, output) goes to :meth:`OnlineSession.feed`,
which returns the one-step prediction, the residual and the monitor's state.
Gaps are found from the stamps as offline (a stamp that goes back, or a step
longer than ``gap_factor`` sample periods): prediction restarts after
``max_lag`` samples and the monitor's whitening filter restarts, so no
prediction uses samples across a gap. Everything is counted
(:meth:`OnlineSession.stats`).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..model.decimation import BlockDecimator, decimate_blocks, decimation_factor
from ..model.narx import NarxModel
from .monitor import MonitorReference, MonitorState, ValidityMonitor
from .predictor import OnlinePredictor
from .tracker import RecursiveTracker

__all__ = ["OnlineSample", "OnlineSession", "held_out_mse"]

#: Stamps kept to date a detected change (older changes get the oldest kept).
STAMP_MEMORY = 100_000


@dataclass(frozen=True)
class OnlineSample:
    """The result of one sample: prediction, residual, the monitor's state."""

    stamp_ns: int
    measured: float
    predicted: float
    residual: float
    normalized: float  # residual over the identification's residual RMS
    state: MonitorState | None
    changed: bool  # the state differs from the previous sample's
    predicted_k: float = math.nan  # the k-step prediction (horizon > 1), NaN until ready


class OnlineSession:
    """Prediction, monitoring and (optionally) tracking of one model.

    Parameters
    ----------
    model : NarxModel
    residuals : ndarray or None
        The identification's one-step residuals. The monitor's reference is
        the one the model document carries (``metadata["monitor"]``, written
        by the job from these same residuals), so a fresh model and one
        restored from a file are monitored alike; without it, these
        residuals; without either (a document written before the documents
        carried it), the document's one-step RMS, the residuals taken as
        white (:attr:`reference_source` says which).
    monitor_window : int
    tracking : bool
        Run the recursive tracker (needs the model's coefficient covariance).
    forgetting : float
    sample_period : float
        Seconds; 0: estimated from the stamps (median step of the first 50).
    gap_factor : float
    horizon : int
        Also predict k = ``horizon`` steps ahead: y(t) from the measured samples
        up to t - k and the model's own outputs in between (1: one-step only).
    decimate : int or None
        Samples per block of the model's rate (None: as its document says,
        ``metadata.decimation``). Above 1 the stream is decimated as the
        identification's record was (:class:`~spm_sysid.core.model.decimation.BlockDecimator`)
        and a prediction comes once per block; a gap drops the partial block.
    """

    def __init__(self, model: NarxModel, residuals: np.ndarray | None = None, *,
                 monitor_window: int = 200, tracking: bool = False,
                 forgetting: float = 0.99, sample_period: float = 0.0,
                 gap_factor: float = 1.5, input_std: float | None = None,
                 horizon: int = 1, decimate: int | None = None) -> None:
        self.model = model
        factor = decimation_factor(model.metadata) if decimate is None else int(decimate)
        self.decimator = BlockDecimator(factor) if factor > 1 else None
        self.predictor = OnlinePredictor(model)
        self._compiled = model.compiled
        stored = model.metadata.get("monitor") if isinstance(model.metadata, dict) else None
        if stored is not None:
            try:
                reference = MonitorReference.from_dict(stored)
            except ValueError as exc:
                raise ValueError(f"the model document's monitor reference is invalid ({exc})") \
                    from None
            self.reference_source = "document"
        elif residuals is not None and len(residuals) >= 2:
            reference = MonitorReference.from_residuals(residuals, (int(monitor_window),))
            self.reference_source = "residuals"
        else:
            rms = math.sqrt(model.mse) if model.mse else 1.0
            reference = MonitorReference.from_residuals(np.array([rms, -rms]), ())
            self.reference_source = "none"  # RMS only; no whitening, fixed thresholds
        self.sigma = reference.sigma
        self.monitor = ValidityMonitor(reference, window=monitor_window)
        self.tracker = None
        if tracking:
            unc = model.uncertainty
            rows = max((model.n_samples or 0) - model.term_space.max_lag, 0)
            self.tracker = RecursiveTracker(
                model.coefficients, None if unc is None else unc.covariance,
                unc.sigma2 if unc is not None else self.sigma ** 2,
                input_std if input_std is not None else reference.input_std,
                forgetting=forgetting, rows=rows)
        self.horizon = int(horizon)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        window = model.term_space.max_lag + self.horizon
        self._win_u: deque = deque(maxlen=window)
        self._win_y: deque = deque(maxlen=window)
        self.period_ns = int(sample_period * 1e9)
        self.gap_factor = gap_factor
        self._steps: list[int] = []
        self._last: int | None = None
        self._stamps: deque[int] = deque(maxlen=STAMP_MEMORY)  # of monitor updates
        self._state = "VALID"
        self.transitions: list[tuple[int, str, str]] = []  # (stamp, from, to)
        self.samples = self.predictions = self.gaps = 0
        self.seconds = 0.0  # time spent in feed

    # -- the stream ------------------------------------------------------------------
    def _gap(self, stamp: int) -> bool:
        last, self._last = self._last, stamp
        if last is None:
            return False
        step = stamp - last
        if step <= 0:
            return True
        if not self.period_ns:
            self._steps.append(step)
            if len(self._steps) < 50:
                return False
            self.period_ns = int(np.median(self._steps))
        return step > self.gap_factor * self.period_ns

    def feed(self, stamp_ns: int, u, y: float) -> OnlineSample | None:
        """One paired sample; None while the history is too short for a prediction."""
        t0 = time.perf_counter()
        self.samples += 1
        if self._gap(stamp_ns):
            self.gaps += 1
            self.predictor.reset()
            self.monitor.gap()
            self._win_u.clear()
            self._win_y.clear()
            if self.decimator is not None:
                self.decimator.reset()
        if self.decimator is not None:  # one prediction per block, at its end
            block = self.decimator.push(stamp_ns, u, y)
            if block is None:
                self.seconds += time.perf_counter() - t0
                return None
            stamp_ns, u, y = block
        if self.horizon > 1:
            self._win_u.append(u)
            self._win_y.append(y)
        out = self.predictor.step(u, y)
        if out is None:
            self.seconds += time.perf_counter() - t0
            return None
        yhat, phi = out
        e = y - yhat
        state = self.monitor.update(e)
        self._stamps.append(stamp_ns)
        if self.tracker is not None:
            self.tracker.update(phi, y, u)
        changed = state.state != self._state
        if changed:
            self.transitions.append((stamp_ns, self._state, state.state))
            self._state = state.state
        self.predictions += 1
        k_step = self._k_step() if self.horizon > 1 else math.nan
        self.seconds += time.perf_counter() - t0
        return OnlineSample(stamp_ns, float(y), yhat, e, e / self.sigma, state, changed,
                            k_step)

    def _k_step(self) -> float:
        """The k-step prediction of the newest sample (NaN until the window is full)."""
        if len(self._win_y) < self._win_y.maxlen:
            return math.nan
        from ..model.simulation import run_model

        u = np.asarray(self._win_u, dtype=float).reshape(len(self._win_y), -1)
        y = np.asarray(self._win_y, dtype=float)
        # a window of max_lag + k samples run free from its first max_lag: its last row is
        # y(t) predicted from the samples up to t - k
        yhat, _ = run_model(self._compiled, self.predictor.coefficients, u, y, None,
                            (-math.inf, math.inf))
        return float(yhat[-1])

    # -- what it knows ---------------------------------------------------------------
    @property
    def state(self) -> MonitorState:
        return self.monitor.state()

    def change_stamp(self) -> int | None:
        """Stamp where the detected change began (None without one)."""
        at = self.monitor.state().change_index
        if at < 0 or not self._stamps:
            return None
        offset = self.monitor.n - len(self._stamps)  # monitor updates before the kept stamps
        return self._stamps[max(at - offset, 0)] if at - offset < len(self._stamps) else \
            self._stamps[-1]

    def stats(self) -> dict:
        """Counters for diagnostics."""
        return {"samples": self.samples, "predictions": self.predictions, "gaps": self.gaps,
                "transitions": len(self.transitions),
                "microseconds_per_sample": (1e6 * self.seconds / self.samples
                                            if self.samples else math.nan),
                "tracker_updates": self.tracker.updates if self.tracker else 0,
                "tracker_frozen": self.tracker.frozen if self.tracker else 0,
                "decimate": self.decimator.factor if self.decimator else 1,
                "decimation_dropped": self.decimator.dropped if self.decimator else 0}


def held_out_mse(model: NarxModel, u: np.ndarray, y: np.ndarray,
                 decimate: int | None = None) -> float:
    """One-step MSE of ``model`` on held-out samples (inf when it cannot predict them).

    How an automatic re-identification is compared with the current model. The
    samples are decimated by ``decimate`` first (None: as the model's document
    says), so a model of a slower rate is judged at its rate.
    """
    factor = decimation_factor(model.metadata) if decimate is None else int(decimate)
    if factor > 1:
        u, y, _, _ = decimate_blocks(np.asarray(u, dtype=float), np.asarray(y, dtype=float),
                                     [(0, len(y))], factor)
    try:
        e = model.residuals(u, y)
    except (ValueError, IndexError):
        return math.inf
    return float(np.mean(e * e)) if len(e) and np.all(np.isfinite(e)) else math.inf

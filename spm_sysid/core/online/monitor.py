"""Is the model still valid? A monitor of the live one-step residuals.

The residuals e(t) of an unchanged system look like the identification's:
the same spread and the same correlation. The monitor compares them with it:

* **Whitening.** An AR(p) filter fitted to the identification's residuals
  (least squares, p = 10 at most) turns them into innovations w(t) with
  standard deviation s; z(t) = w(t) / s is then about white N(0, 1) while
  the system is unchanged. (A model's residuals are rarely white: the robot
  arm's AIC model has a lag-1 residual correlation of about 0.6, which would
  make a detector on raw residuals raise false alarms.)
* **CUSUM** (Page) on z: two-sided for a mean shift of one standard deviation
  (k = 0.5) and one-sided for a doubled variance (log-likelihood ratio
  z^2 / 4 - ln(2) / 2). A statistic above its threshold means a change:
  state ``INVALID``, latched until a new model is set, with the change time
  estimated as the last time that statistic was zero. The thresholds
  (:data:`H_MEAN`, :data:`H_VARIANCE`) are set for an average run length of
  about 10^6 samples between false alarms on white Gaussian z
  (Siegmund's approximation for the mean, simulation for both; measured:
  ``python -m spm_sysid.bench.online``).
* **Window** of the last ``window`` samples: RMS of e against the
  identification's, and the Ljung-Box statistic of z over 10 lags. RMS ratio
  above :data:`DEGRADED_RMS` or a whiteness p-value below
  :data:`DEGRADED_P` give ``DEGRADED`` (not latched: it clears when the
  window looks right again).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DEGRADED_P", "DEGRADED_RMS", "H_MEAN", "H_VARIANCE", "MonitorState",
           "ValidityMonitor", "fit_whitening"]

#: CUSUM thresholds (mean shift of 1 sd, k = 0.5; variance doubled).
H_MEAN = 12.0
H_VARIANCE = 14.0
K_MEAN = 0.5
LLR_VARIANCE = 0.5 * math.log(2.0)
#: Windowed checks that make the state DEGRADED.
DEGRADED_RMS = 1.3
DEGRADED_P = 1e-3
LJUNG_BOX_LAGS = 10
MAX_AR = 10

VALID, DEGRADED, INVALID = "VALID", "DEGRADED", "INVALID"


def fit_whitening(residuals: np.ndarray, order: int = MAX_AR) -> tuple[np.ndarray, float]:
    """AR coefficients a (e(t) ~ sum a_i e(t-i)) and the innovations' standard deviation.

    Least squares on the identification's residuals; the order is reduced for
    short records (at least 20 rows per coefficient); order 0 when fewer than 40
    residuals.
    """
    e = np.asarray(residuals, dtype=float)
    e = e[np.isfinite(e)]
    p = int(min(order, max(len(e) // 20 - 1, 0)))
    if p < 1:
        return np.zeros(0), float(np.sqrt(np.mean(e * e))) if len(e) else 1.0
    X = np.column_stack([e[p - i - 1:len(e) - i - 1] for i in range(p)])
    a, *_ = np.linalg.lstsq(X, e[p:], rcond=None)
    w = e[p:] - X @ a
    return a, float(np.sqrt(np.mean(w * w)))


@dataclass(frozen=True)
class MonitorState:
    """What the monitor says after a sample.

    Attributes
    ----------
    state : str
        ``VALID``, ``DEGRADED`` or ``INVALID``.
    samples : int
        Residuals seen since the model was set.
    rms_ratio : float
        RMS of the window's residuals over the identification's (NaN until
        the window is full).
    whiteness_p : float
        Ljung-Box p-value of the window's whitened residuals (NaN until computed).
    cusum_mean, cusum_variance : float
        The statistics as fractions of their thresholds (1 = alarm).
    change_index : int
        Sample (counted from the model being set) where the detected change
        began; -1 when none.
    reason : str
        Why the state is not VALID ('' when it is).
    """

    state: str
    samples: int
    rms_ratio: float
    whiteness_p: float
    cusum_mean: float
    cusum_variance: float
    change_index: int
    reason: str


class ValidityMonitor:
    """Residual monitor of one model (see the module doc).

    Parameters
    ----------
    residuals : ndarray
        The identification's one-step residuals (their spread and correlation
        are the reference).
    window : int
        Samples of the RMS and whiteness window.
    """

    def __init__(self, residuals: np.ndarray, window: int = 200) -> None:
        e = np.asarray(residuals, dtype=float)
        e = e[np.isfinite(e)]
        if len(e) < 2:
            raise ValueError("the monitor needs the identification's residuals (at least 2)")
        self.sigma = float(np.sqrt(np.mean(e * e))) or 1.0
        self.ar, s = fit_whitening(e)
        self.s = s or self.sigma
        self.window = int(window)
        self._past = np.zeros(len(self.ar))  # e(t-1), e(t-2), ...
        self._e = np.zeros(self.window)
        self._z = np.zeros(self.window)
        self.reset()

    def reset(self) -> None:
        """Start again (a new model)."""
        self.n = 0
        self._past[:] = 0.0
        self._warm = 0  # residuals in the whitening filter's memory
        self._gp = self._gn = self._gv = 0.0
        self._zero = {"mean": 0, "variance": 0}  # last index each statistic was zero
        self._alarm: tuple[str, int] | None = None
        self._p = math.nan
        self._filled = 0
        self._e[:] = 0.0
        self._sumsq = 0.0

    def gap(self) -> None:
        """A gap in the stream: the whitening filter's memory restarts (CUSUMs kept)."""
        self._past[:] = 0.0
        self._warm = 0

    def update(self, e: float) -> MonitorState:
        """Add one residual; the state after it."""
        n = self.n
        p = len(self.ar)
        if p:
            w = e - float(np.dot(self.ar, self._past))
            self._past[1:] = self._past[:-1]
            self._past[0] = e
        else:
            w = e
        if self._warm < p:  # the filter needs p residuals before it whitens
            self._warm += 1
            self.n = n + 1
            return self.state()
        z = w / self.s
        self._gp = max(0.0, self._gp + z - K_MEAN)
        self._gn = max(0.0, self._gn - z - K_MEAN)
        self._gv = max(0.0, self._gv + 0.25 * z * z - LLR_VARIANCE)
        if self._gp == 0.0 and self._gn == 0.0:
            self._zero["mean"] = n + 1
        if self._gv == 0.0:
            self._zero["variance"] = n + 1
        if self._alarm is None:
            if max(self._gp, self._gn) > H_MEAN:
                self._alarm = ("mean", self._zero["mean"])
            elif self._gv > H_VARIANCE:
                self._alarm = ("variance", self._zero["variance"])
        col = n % self.window
        self._sumsq += e * e - self._e[col] * self._e[col]
        self._e[col], self._z[col] = e, z
        self._filled = min(self._filled + 1, self.window)
        self.n = n + 1
        if self._filled == self.window and self.n % (self.window // 2) == 0:
            self._p = ljung_box_p(np.roll(self._z, -(col + 1)), LJUNG_BOX_LAGS)
        return self.state()

    def state(self) -> MonitorState:
        """The current state (see :class:`MonitorState`)."""
        rms = (math.sqrt(max(self._sumsq, 0.0) / self.window) / self.sigma
               if self._filled == self.window else math.nan)
        if self._alarm is not None:
            kind, at = self._alarm
            state, change = INVALID, at
            reason = (f"change detected by the CUSUM of the residual's {kind} "
                      f"(began about sample {at} of {self.n})")
        else:
            change, reasons = -1, []
            if rms > DEGRADED_RMS:
                reasons.append(f"residual RMS {rms:.2f} x the identification's")
            if self._p < DEGRADED_P:
                reasons.append(f"residuals not white (Ljung-Box p = {self._p:.1e})")
            state = DEGRADED if reasons else VALID
            reason = "; ".join(reasons)
        return MonitorState(state, self.n, rms, self._p, max(self._gp, self._gn) / H_MEAN,
                            self._gv / H_VARIANCE, change, reason)


def ljung_box_p(z: np.ndarray, lags: int) -> float:
    """Ljung-Box p-value of ``z`` over ``lags`` lags (chi-squared with ``lags`` dof)."""
    from scipy.special import chdtrc

    z = np.asarray(z, dtype=float) - np.mean(z)
    n = len(z)
    denom = float(z @ z)
    if n <= lags + 1 or denom <= 0:
        return math.nan
    q = sum((float(z[k:] @ z[:-k]) / denom) ** 2 / (n - k) for k in range(1, lags + 1))
    return float(chdtrc(lags, n * (n + 2) * q))

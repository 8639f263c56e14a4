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
  ``python -m benchmarks.online``).
* **Window** of the last ``window`` samples: RMS of e against the
  identification's, and the Ljung-Box statistic of z over 10 lags. RMS ratio
  above :data:`DEGRADED_RMS` or a whiteness p-value below
  :data:`DEGRADED_P` give ``DEGRADED`` (not latched: it clears when the
  window looks right again).
* **The identification's own statistics** (:class:`MonitorReference`). A
  model's residuals are often neither white after an AR(10) nor of constant
  spread (the robot arm's are not: its Ljung-Box p falls to 1e-7 in some
  windows of its own estimation data). So every statistic above is also
  computed over every window of the identification's residuals, and a
  threshold is never below the most extreme value seen there (times
  :data:`REFERENCE_MARGIN`): a model on the data it was fitted on stays
  ``VALID``, and a change must look worse than anything the identification
  saw. The reference travels in the model document
  (``metadata["monitor"]``), so a model restored from a file is monitored
  exactly as the fresh one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.metadata import check_monitor

__all__ = ["DEGRADED_P", "DEGRADED_RMS", "H_MEAN", "H_VARIANCE", "MonitorReference",
           "MonitorState", "ValidityMonitor", "fit_whitening", "store_monitor_reference"]

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
#: A threshold is at least this times the worst value on the identification's residuals.
REFERENCE_MARGIN = 1.05
#: Window lengths whose reference statistics a model document carries.
REFERENCE_WINDOWS = (50, 100, 200, 500, 1000, 2000, 5000)
#: The document's format of the reference (``metadata["monitor"]["version"]``).
REFERENCE_VERSION = 1


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


def _whiten(e: np.ndarray, ar: np.ndarray, s: float) -> np.ndarray:
    """z(t) = (e(t) - sum a_i e(t-i)) / s for t >= p, as the monitor computes it."""
    p = len(ar)
    w = e[p:].copy()
    for i, a in enumerate(ar):
        w -= a * e[p - i - 1:len(e) - i - 1]
    return w / s


def _sliding_ljung_box(z: np.ndarray, window: int, lags: int = LJUNG_BOX_LAGS) -> np.ndarray:
    """The Ljung-Box statistic Q of every window of ``window`` samples of ``z``.

    The same statistic as :func:`ljung_box_p` computes for one window (mean
    removed per window), for all windows at once from running sums.
    """
    n, w = len(z), int(window)
    if n < w or w <= lags + 1:
        return np.zeros(0)
    c1 = np.concatenate([[0.0], np.cumsum(z)])
    c2 = np.concatenate([[0.0], np.cumsum(z * z)])
    a = np.arange(n - w + 1)
    total = c1[a + w] - c1[a]
    m = total / w
    denom = (c2[a + w] - c2[a]) - w * m * m
    q = np.zeros(len(a))
    for k in range(1, lags + 1):
        ck = np.concatenate([[0.0], np.cumsum(z[k:] * z[:-k])])  # ck[j]: sum of t < j + k
        cross = ck[a + w - k] - ck[a]
        head = c1[a + w] - c1[a + k]  # z(t), t = a+k .. a+w-1
        tail = c1[a + w - k] - c1[a]  # z(t-k)
        num = cross - m * (head + tail) + (w - k) * m * m
        with np.errstate(invalid="ignore", divide="ignore"):
            q += (num / denom) ** 2 / (w - k)
    return np.where(denom > 0, w * (w + 2) * q, 0.0)


def _sliding_rms(e: np.ndarray, window: int) -> np.ndarray:
    c = np.concatenate([[0.0], np.cumsum(e * e)])
    if len(e) < window:
        return np.zeros(0)
    return np.sqrt(np.maximum(c[window:] - c[:-window], 0.0) / window)


def _cusum_maxima(z: np.ndarray) -> tuple[float, float]:
    """The largest mean and variance CUSUM statistics over ``z`` (as the monitor runs them)."""
    gp = gn = gv = top_m = top_v = 0.0
    for x in z.tolist():
        gp = max(0.0, gp + x - K_MEAN)
        gn = max(0.0, gn - x - K_MEAN)
        gv = max(0.0, gv + 0.25 * x * x - LLR_VARIANCE)
        top_m, top_v = max(top_m, gp, gn), max(top_v, gv)
    return top_m, top_v


@dataclass(frozen=True)
class MonitorReference:
    """The identification's residual statistics that the monitor compares a stream with.

    Attributes
    ----------
    sigma : float
        RMS of the identification's one-step residuals.
    ar : tuple of float
        The whitening filter (:func:`fit_whitening`).
    innovation_sd : float
        Standard deviation of the whitened residuals.
    cusum_mean, cusum_variance : float
        The largest CUSUM statistics over the identification's residuals.
    windows : dict
        ``{window: (largest Ljung-Box Q, largest RMS ratio)}`` over every window of
        that many samples of the identification's residuals.
    samples : int
        Residuals the reference was computed from.
    input_std : float or None
        The identification input's largest standard deviation (the tracker's
        quiet check; None when unknown).
    """

    sigma: float
    ar: tuple[float, ...]
    innovation_sd: float
    cusum_mean: float
    cusum_variance: float
    windows: dict
    samples: int
    input_std: float | None = None

    @classmethod
    def from_residuals(cls, residuals: np.ndarray,
                       windows: tuple[int, ...] = REFERENCE_WINDOWS,
                       inputs: np.ndarray | None = None) -> MonitorReference:
        """The reference of these one-step residuals (non-finite ones left out).

        ``inputs`` (n,) or (n, m): the identification's inputs, for ``input_std``.
        """
        e = np.asarray(residuals, dtype=float).ravel()
        e = e[np.isfinite(e)]
        if len(e) < 2:
            raise ValueError("the monitor needs the identification's residuals (at least 2)")
        sigma = float(np.sqrt(np.mean(e * e))) or 1.0
        ar, s = fit_whitening(e)
        s = s or sigma
        z = _whiten(e, ar, s)
        table = {}
        for w in sorted(set(int(x) for x in windows)):
            q, r = _sliding_ljung_box(z, w), _sliding_rms(e[len(ar):], w)
            if len(q) and len(r):
                table[w] = (float(np.max(q)), float(np.max(r)) / sigma)
        top_m, top_v = _cusum_maxima(z)
        spread = None
        if inputs is not None:
            u = np.asarray(inputs, dtype=float)
            u = u.reshape(len(u), -1)[np.all(np.isfinite(u.reshape(len(u), -1)), axis=1)]
            spread = float(np.max(np.std(u, axis=0))) if u.size else None
        return cls(sigma, tuple(float(a) for a in ar), float(s), top_m, top_v, table, len(e),
                   spread or None)

    def for_window(self, window: int) -> tuple[float, float] | None:
        """(largest Q, largest RMS ratio) to expect in windows of ``window`` samples.

        A window the table holds is exact; otherwise the nearest shorter one
        (Q scaled by the length ratio: it grows at most in proportion), else None.
        """
        if window in self.windows:
            return self.windows[window]
        shorter = [w for w in self.windows if w < window]
        if not shorter:
            return None
        w = max(shorter)
        q, r = self.windows[w]
        return q * window / w, r

    def to_dict(self) -> dict:
        """For the model document's ``metadata["monitor"]``."""
        return {"version": REFERENCE_VERSION, "samples": self.samples, "sigma": self.sigma,
                "whitening_ar": list(self.ar), "innovation_sd": self.innovation_sd,
                "cusum_mean_max": self.cusum_mean, "cusum_variance_max": self.cusum_variance,
                "windows": [{"window": w, "ljung_box_max": q, "rms_ratio_max": r}
                            for w, (q, r) in sorted(self.windows.items())],
                "input_std": self.input_std}

    @classmethod
    def from_dict(cls, doc) -> MonitorReference:
        """Read :meth:`to_dict`'s output; ValueError naming what is wrong."""
        if not isinstance(doc, dict) or doc.get("version") != REFERENCE_VERSION:
            raise ValueError(f"monitor reference of an unknown format (version must be "
                             f"{REFERENCE_VERSION})")
        check_monitor(doc)  # types, and only values that residuals can give
        table = {int(w["window"]): (float(w["ljung_box_max"]), float(w["rms_ratio_max"]))
                 for w in doc["windows"]}
        spread = doc.get("input_std")
        return cls(float(doc["sigma"]), tuple(float(a) for a in doc["whitening_ar"]),
                   float(doc["innovation_sd"]), float(doc["cusum_mean_max"]),
                   float(doc["cusum_variance_max"]), table, int(doc["samples"]),
                   None if spread is None else float(spread) or None)


def store_monitor_reference(metadata: dict, residuals: np.ndarray,
                            inputs: np.ndarray | None = None) -> None:
    """The reference of these validation residuals into a model's ``metadata["monitor"]``.

    What a model restored from its file is monitored against, as the fresh one
    is (nothing is stored with fewer than two finite residuals). ``inputs``:
    the identification's inputs (their spread, for the tracker).
    """
    e = np.asarray(residuals, dtype=float)
    if np.count_nonzero(np.isfinite(e)) >= 2:
        metadata["monitor"] = MonitorReference.from_residuals(e, inputs=inputs).to_dict()


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
    residuals : ndarray or MonitorReference
        The identification's one-step residuals (their spread and correlation
        are the reference), or the reference computed from them.
    window : int
        Samples of the RMS and whiteness window.
    """

    def __init__(self, residuals: np.ndarray | MonitorReference, window: int = 200) -> None:
        ref = (residuals if isinstance(residuals, MonitorReference)
               else MonitorReference.from_residuals(residuals, (int(window),)))
        self.reference = ref
        self.sigma = ref.sigma
        self.ar, self.s = np.asarray(ref.ar, dtype=float), ref.innovation_sd
        self.window = int(window)
        seen = ref.for_window(self.window)
        # thresholds: the fixed ones, or beyond the worst the identification's residuals
        # showed (a model on its own data stays VALID)
        self.h_mean = max(H_MEAN, REFERENCE_MARGIN * ref.cusum_mean)
        self.h_variance = max(H_VARIANCE, REFERENCE_MARGIN * ref.cusum_variance)
        self.q_limit = max(_chi2_isf(DEGRADED_P, LJUNG_BOX_LAGS),
                           REFERENCE_MARGIN * seen[0] if seen else 0.0)
        self.rms_limit = max(DEGRADED_RMS, REFERENCE_MARGIN * seen[1] if seen else 0.0)
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
        self._p = self._q = math.nan
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
            if max(self._gp, self._gn) > self.h_mean:
                self._alarm = ("mean", self._zero["mean"])
            elif self._gv > self.h_variance:
                self._alarm = ("variance", self._zero["variance"])
        col = n % self.window
        self._sumsq += e * e - self._e[col] * self._e[col]
        self._e[col], self._z[col] = e, z
        self._filled = min(self._filled + 1, self.window)
        self.n = n + 1
        if self._filled == self.window and self.n % (self.window // 2) == 0:
            self._q = ljung_box_q(np.roll(self._z, -(col + 1)), LJUNG_BOX_LAGS)
            self._p = _chi2_sf(self._q, LJUNG_BOX_LAGS)
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
            if rms > self.rms_limit:
                reasons.append(f"residual RMS {rms:.2f} x the identification's (limit "
                               f"{self.rms_limit:.2f})")
            if self._q > self.q_limit:
                reasons.append(f"residuals more correlated than on the identification data "
                               f"(Ljung-Box p = {self._p:.1e}, Q = {self._q:.1f} > "
                               f"{self.q_limit:.1f})")
            state = DEGRADED if reasons else VALID
            reason = "; ".join(reasons)
        return MonitorState(state, self.n, rms, self._p,
                            max(self._gp, self._gn) / self.h_mean, self._gv / self.h_variance,
                            change, reason)


def ljung_box_q(z: np.ndarray, lags: int) -> float:
    """The Ljung-Box statistic of ``z`` over ``lags`` lags (NaN when it cannot be computed)."""
    z = np.asarray(z, dtype=float) - np.mean(z)
    n = len(z)
    denom = float(z @ z)
    if n <= lags + 1 or denom <= 0:
        return math.nan
    q = sum((float(z[k:] @ z[:-k]) / denom) ** 2 / (n - k) for k in range(1, lags + 1))
    return n * (n + 2) * q


def ljung_box_p(z: np.ndarray, lags: int) -> float:
    """Ljung-Box p-value of ``z`` over ``lags`` lags (chi-squared with ``lags`` dof)."""
    return _chi2_sf(ljung_box_q(z, lags), lags)


def _chi2_sf(q: float, dof: int) -> float:
    from scipy.special import chdtrc

    return math.nan if math.isnan(q) else float(chdtrc(dof, q))


def _chi2_isf(p: float, dof: int) -> float:
    from scipy.special import chdtri

    return float(chdtri(dof, p))

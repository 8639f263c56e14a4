"""Recursive least squares on a model's structure: coefficients that follow the robot.

:class:`RecursiveTracker` starts from the identified coefficients and their
covariance and updates both with each sample (exponential forgetting, factor
``forgetting``; memory about 1 / (1 - forgetting) samples). Safeguards:

* **No wind-up when the input is quiet.** Forgetting inflates the covariance
  in every direction, also those the data do not excite; with a constant input
  that grows without bound and the next excitation throws the coefficients
  about. The tracker therefore updates only while the input excites: the
  input's standard deviation over the last ``quiet_window`` samples must be
  at least ``quiet_fraction`` of the identification's. Otherwise it is frozen
  (coefficients and covariance kept; counted in ``frozen``).
* **Bounded covariance.** Its trace is kept at most ``max_trace_factor``
  times the identification's; it is symmetrised after every update, and an
  update that would make it lose positive definiteness (a non-positive
  denominator) is skipped.

The coefficients' covariance is ``sigma2 * P`` with ``sigma2`` the
forgetting-weighted mean of the squared prediction errors.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["LEARN_INPUT", "RecursiveTracker"]

#: Inputs whose spread sets the quiet threshold when the identification's is not given.
LEARN_INPUT = 500
#: Samples between two checks of the input's spread.
QUIET_EVERY = 5
#: Largest coefficient magnitude tracked: beyond it, products in an update overflow.
MAX_COEFFICIENT = 1e100


class RecursiveTracker:
    """Exponentially weighted recursive least squares on a fixed structure.

    Parameters
    ----------
    coefficients : ndarray, shape (k,)
        The identified coefficients (the start).
    covariance : ndarray, shape (k, k), optional
        Their covariance (``sigma2 * (X'X)^-1``); without it a diffuse start.
    sigma2 : float
        The identification's residual variance.
    input_std : float or None
        The identification input's standard deviation (for the quiet check);
        None: the standard deviation of the first :data:`LEARN_INPUT` inputs the
        tracker sees (never quiet before).
    forgetting : float
        Forgetting factor in (0, 1].
    rows : int
        Regression rows of the identification: its information is discounted
        to the tracker's memory (P scaled by ``rows * (1 - forgetting)`` when
        that exceeds 1), so tracking starts at its steady-state pace instead
        of trusting 2 000 old rows as if they were recent.
    """

    def __init__(self, coefficients: np.ndarray, covariance: np.ndarray | None, sigma2: float,
                 input_std: float | None, forgetting: float = 0.99, quiet_window: int = 50,
                 quiet_fraction: float = 0.05, max_trace_factor: float = 1e4,
                 rows: int = 0) -> None:
        if not 0.0 < forgetting <= 1.0:
            raise ValueError(f"forgetting must be in (0, 1], got {forgetting}")
        self.theta = np.asarray(coefficients, dtype=float).copy()
        k = len(self.theta)
        self.sigma2 = float(sigma2) if sigma2 > 0 else 1.0
        if covariance is not None:
            P = np.asarray(covariance, dtype=float) / self.sigma2
            P = P * max(1.0, rows * (1.0 - forgetting))
        else:
            P = np.eye(k) * 1e3
        with np.errstate(over="ignore", invalid="ignore"):
            self.P = 0.5 * (P + P.T)
            self.max_trace = max_trace_factor * float(np.trace(self.P))
        if not (np.all(np.isfinite(self.theta)) and np.all(np.isfinite(self.P))
                and np.isfinite(self.max_trace)
                and np.max(np.abs(self.theta), initial=0.0) <= MAX_COEFFICIENT):
            raise ValueError("the model's coefficients or their covariance are too large to "
                             "track (they overflow double precision)")
        self.lam = float(forgetting)
        self.input_std = None if input_std is None or not input_std > 0 else float(input_std)
        self._first: list = []
        self._quiet: bool | None = None
        self._since_quiet = 0
        self.quiet_fraction = quiet_fraction
        self._u = deque(maxlen=int(quiet_window))
        self.updates = self.frozen = self.skipped = 0

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the tracked coefficients (``sigma2 * P``)."""
        return self.sigma2 * self.P

    @property
    def standard_errors(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    def quiet(self) -> bool:
        """The input has barely moved over the last ``quiet_window`` samples.

        With the identification's input spread known, the first ``quiet_window``
        samples count as quiet too (their spread is not known yet).

        Computed every :data:`QUIET_EVERY` samples (it costs more than an update).
        """
        if self.input_std is None:
            return False
        if len(self._u) < self._u.maxlen:
            return True  # excitation not yet seen: an update could only drift
        self._since_quiet += 1
        if self._quiet is None or self._since_quiet >= QUIET_EVERY:
            u = np.asarray(self._u)
            spread = float(np.max(np.std(u, axis=0))) if u.ndim > 1 else float(np.std(u))
            self._quiet, self._since_quiet = spread < self.quiet_fraction * self.input_std, 0
        return self._quiet

    def update(self, phi: np.ndarray, y: float, u=None) -> bool:
        """One sample: regressors ``phi`` (the model's terms), output ``y``, input ``u``.

        Returns True when the coefficients were updated (False: frozen or skipped).
        """
        if u is not None:
            self._u.append(u)
            if self.input_std is None:
                self._first.append(u)
                if len(self._first) >= LEARN_INPUT:
                    first = np.asarray(self._first, dtype=float)
                    self.input_std = float(np.max(np.std(first, axis=0))) or 1.0
                    self._first = []
        if self.quiet():
            self.frozen += 1
            return False
        with np.errstate(over="ignore", invalid="ignore"):
            e = y - float(phi @ self.theta)
            Pphi = self.P @ phi
            denom = self.lam + float(phi @ Pphi)
            if not denom > 0 or not np.isfinite(denom) or not np.isfinite(e):
                self.skipped += 1
                return False
            gain = Pphi / denom
            theta = self.theta + gain * e
            P = (self.P - np.outer(gain, Pphi)) / self.lam
            P = 0.5 * (P + P.T)
            trace = float(np.trace(P))
            post = y - float(phi @ theta)
            if not (np.all(np.isfinite(theta)) and np.isfinite(trace) and np.isfinite(post)):
                self.skipped += 1  # the update would overflow: the sample is left out
                return False
        if trace > self.max_trace:
            P *= self.max_trace / trace
        self.theta, self.P = theta, P
        # forgetting-weighted error variance (a posteriori error of this sample)
        self.sigma2 = self.lam * self.sigma2 + (1 - self.lam) * e * post
        self.updates += 1
        return True

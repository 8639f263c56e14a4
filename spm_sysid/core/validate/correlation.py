"""Correlation tests for NARX model validity (Billings & Voon, 1986).

A model is adequate when its one-step residuals e are unpredictable from past
inputs and residuals. With ``ccf(a, b)(tau) = corr(a(t), b(t - tau))`` (means
removed, normalised to [-1, 1]), the five classical tests are:

=========  ==============================  ==================  ============
name       correlation                      lags                 expectation
=========  ==============================  ==================  ============
``ee``     ccf(e, e)                        -L..L (checked 1..L) 0
``ue``     ccf(e, u)                        -L..L                0
``e_eu``   ccf(e, e*u)                      1..L+1               0
``u2_e``   ccf(e, u^2 - mean(u^2))          -L..L                0
``u2_e2``  ccf(e^2, u^2 - mean(u^2))        -L..L                0
=========  ==============================  ==================  ============

``e_eu`` at lag 1+tau is E[e(t) e(t-1-tau) u(t-1-tau)], the classical
phi_{e(eu)}(tau) for tau >= 0. A value is inside the 95 % confidence band when
``|value| <= 1.96 / sqrt(N)``. The autocorrelation is symmetric, so only its lags
1..L are checked. Each test reports the fraction of its checked lags inside the
band. Even white noise leaves about 5 % of lags outside, so a test *passes* when
no more lags are outside than white noise would leave in 95 % of records: at most
the 95th percentile of Binomial(n_lags, 0.05) (e.g. 4 of 41 lags).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CorrelationTest", "ccf", "correlation_tests", "TEST_LABELS"]

TEST_LABELS = {
    "ee": "residual autocorrelation  φ_εε(τ)",
    "ue": "input–residual  φ_uε(τ)",
    "e_eu": "residual–(residual·input)  φ_ε(εu)(τ)",
    "u2_e": "squared input–residual  φ_(u²)'ε(τ)",
    "u2_e2": "squared input–squared residual  φ_(u²)'(ε²)(τ)",
}


def ccf(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation ``corr(a(t), b(t - tau))`` for each tau in ``lags``.

    Means are removed and the sum of products is divided by
    ``sqrt(sum a^2 * sum b^2)`` over the whole record (the standard biased
    estimator), so values lie in [-1, 1]. A constant signal gives zeros.
    """
    a = np.asarray(a, dtype=float) - np.mean(a)
    b = np.asarray(b, dtype=float) - np.mean(b)
    n = len(a)
    denom = np.sqrt(np.dot(a, a) * np.dot(b, b))
    out = np.zeros(len(lags))
    if denom == 0:
        return out
    for i, tau in enumerate(np.asarray(lags, dtype=int)):
        if abs(tau) >= n:
            continue
        out[i] = np.dot(a[tau:], b[: n - tau]) if tau >= 0 else np.dot(a[: n + tau], b[-tau:])
    return out / denom


@dataclass(frozen=True)
class CorrelationTest:
    """One correlation test over a lag range."""

    name: str
    lags: np.ndarray
    values: np.ndarray
    band: float

    @property
    def label(self) -> str:
        """Readable name with the classical symbol."""
        return TEST_LABELS.get(self.name, self.name)

    @property
    def checked(self) -> np.ndarray:
        """Lags that count.

        The autocorrelation at lag 0 is always 1; the residuals of two outputs
        may share noise at the same instant (``cross_*``).
        """
        if self.name == "ee":
            return self.lags > 0
        if self.name.startswith("cross_"):
            return self.lags != 0
        return np.ones(len(self.lags), dtype=bool)

    @property
    def fraction_inside(self) -> float:
        """Fraction of the checked lags inside the 95 % band."""
        inside = np.abs(self.values[self.checked]) <= self.band
        return float(inside.mean()) if inside.size else 1.0

    @property
    def allowed_outside(self) -> int:
        """Lags outside the band that white noise exceeds in only 5 % of records."""
        return binomial_quantile(0.95, int(self.checked.sum()), 0.05)

    @property
    def passed(self) -> bool:
        """No more lags outside the band than :attr:`allowed_outside`."""
        outside = int((np.abs(self.values[self.checked]) > self.band).sum())
        return outside <= self.allowed_outside

    @property
    def worst_lag(self) -> int:
        """Lag of the largest |value| among the checked lags."""
        vals = np.where(self.checked, np.abs(self.values), -1.0)
        return int(self.lags[int(np.argmax(vals))])

    def to_dict(self) -> dict:
        """Summary for JSON documents (not the full curve)."""
        return {
            "name": self.name,
            "fraction_inside": round(self.fraction_inside, 4),
            "passed": self.passed,
            "band": self.band,
            "max_abs": float(np.max(np.abs(self.values[self.checked]), initial=0.0)),
            "worst_lag": self.worst_lag,
        }


def correlation_tests(
    residuals: np.ndarray, u: np.ndarray, max_lag: int = 20
) -> list[CorrelationTest]:
    """The five tests for residuals e and the input u aligned with them (same t)."""
    e = np.asarray(residuals, dtype=float)
    u = np.asarray(u, dtype=float)
    if len(e) != len(u):
        raise ValueError(f"residuals and input differ in length: {len(e)} and {len(u)}")
    if max_lag < 1:
        raise ValueError(f"max_lag must be >= 1, got {max_lag}")
    # the tests are scale-free: scale first so products of data of any magnitude
    # (1e-100 or 1e100) neither overflow nor underflow
    e = e / (np.max(np.abs(e)) or 1.0)
    u = u / (np.max(np.abs(u)) or 1.0)
    band = 1.96 / np.sqrt(len(e))
    sym = np.arange(-max_lag, max_lag + 1)
    u2 = u**2 - np.mean(u**2)
    return [
        CorrelationTest("ee", sym, ccf(e, e, sym), band),
        CorrelationTest("ue", sym, ccf(e, u, sym), band),
        CorrelationTest("e_eu", np.arange(1, max_lag + 2), ccf(e, e * u, np.arange(1, max_lag + 2)),
                        band),
        CorrelationTest("u2_e", sym, ccf(e, u2, sym), band),
        CorrelationTest("u2_e2", sym, ccf(e**2, u2, sym), band),
    ]


def binomial_quantile(q: float, n: int, p: float) -> int:
    """The smallest k with P(X <= k) >= q for X ~ Binomial(n, p) (scipy's ``binom.ppf``).

    Summed from log-gamma terms: exact enough for any n, and it spares every
    command the import of scipy.stats (about 0.3 s).
    """
    if n <= 0:
        return 0
    log_p, log_q = math.log(p), math.log1p(-p)
    total = 0.0
    for k in range(n + 1):
        total += math.exp(math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)
                          + k * log_p + (n - k) * log_q)
        if total >= q * (1.0 - 1e-12):
            return k
    return n

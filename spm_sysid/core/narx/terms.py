"""Candidate terms of a polynomial NARX model and the regression matrix.

The term order is fixed and documented because a GA chromosome is one bit per
term in exactly this order:

1. the constant term ``1`` (only when ``constant=True``);
2. the linear terms: ``y(t-1) .. y(t-ny)`` then ``u(t-d) .. u(t-d-nu+1)``;
3. the products of degree 2, 3, ... ``degree``: for each degree, every
   multiset of linear terms in lexicographic order of their positions in
   step 2 (``itertools.combinations_with_replacement``), e.g. ``y(t-1)^2``,
   ``y(t-1)*y(t-2)``, ..., ``u(t-4)^2``.

With the paper's setting (ny=4, nu=4, degree=2, delay=1, no constant) this gives
8 linear and 36 quadratic terms: 44 in all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from itertools import combinations_with_replacement

import numpy as np

from ..settings import check_all

__all__ = ["MAX_TERMS", "TermSpace", "power_of_two_scale"]

#: Largest term space (the memory bound usually refuses earlier, with the size needed).
MAX_TERMS = 100_000


def power_of_two_scale(x: np.ndarray) -> float:
    """The power of two nearest the RMS of ``x`` (1 for an all-zero signal).

    Dividing by a power of two is exact in floating point, so scaled data give
    the same fits as the original bit for bit, while data of any magnitude
    (1e-100 or 1e100) stay clear of overflow and underflow in the products.
    """
    x = np.asarray(x, dtype=float)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    if not peak > 0 or not np.isfinite(peak):
        return 1.0
    rms = peak * float(np.sqrt(np.mean(np.square(x / peak))))
    return float(np.ldexp(1.0, int(np.round(np.log2(rms)))))


@dataclass(frozen=True)
class TermSpace:
    """The space of candidate NARX terms.

    Parameters
    ----------
    ny : int
        Maximum output lag; output lags are 1..ny.
    nu : int
        Number of input lags; input lags are delay..delay+nu-1.
    degree : int
        Highest polynomial degree (the paper's "nonlinearity").
    delay : int
        Input delay (the smallest input lag), at least 1 so the model is causal.
    constant : bool
        Whether a constant term is a candidate.
    """

    ny: int = 4
    nu: int = 4
    degree: int = 2
    delay: int = 1
    constant: bool = False

    def __post_init__(self) -> None:
        # ranges and types are declared once, in the settings schema
        for name, value in check_all(asdict(self)).items():
            object.__setattr__(self, name, value)
        if self.ny + self.nu == 0:
            raise ValueError("at least one of ny, nu must be positive")
        if self.n_terms > MAX_TERMS:
            raise ValueError(
                f"this term space has {self.n_terms} candidate terms; at most {MAX_TERMS} "
                "are supported (lower the lags or the degree)")

    # -- the linear building blocks -------------------------------------------------
    @property
    def linear(self) -> list[tuple[str, int]]:
        """The lagged signals as ``(signal, lag)`` pairs, in term order."""
        ys = [("y", lag) for lag in range(1, self.ny + 1)]
        us = [("u", lag) for lag in range(self.delay, self.delay + self.nu)]
        return ys + us

    @property
    def max_lag(self) -> int:
        """Largest lag; the first regression row is at t = max_lag."""
        return max(self.ny, self.delay + self.nu - 1 if self.nu else 0)

    @property
    def terms(self) -> list[tuple[int, ...]]:
        """Every candidate term as a sorted tuple of indices into :attr:`linear`.

        The constant term is the empty tuple.
        """
        n_lin = len(self.linear)
        out: list[tuple[int, ...]] = [()] if self.constant else []
        for deg in range(1, self.degree + 1):
            out.extend(combinations_with_replacement(range(n_lin), deg))
        return out

    @property
    def n_terms(self) -> int:
        """Number of candidate terms (chromosome length)."""
        from math import comb

        n_lin = (self.ny + self.nu)
        return int(self.constant) + sum(
            comb(n_lin + deg - 1, deg) for deg in range(1, self.degree + 1)
        )

    def term_names(self) -> list[str]:
        """Readable names such as ``y(t-1)*u(t-2)`` and ``u(t-1)^2``, in term order."""
        lin = self.linear
        names = []
        for term in self.terms:
            if not term:
                names.append("1")
                continue
            parts = []
            for idx in sorted(set(term)):
                sig, lag = lin[idx]
                power = term.count(idx)
                parts.append(f"{sig}(t-{lag})" + (f"^{power}" if power > 1 else ""))
            names.append("*".join(parts))
        return names

    def to_dict(self) -> dict:
        """Plain-data form for JSON documents."""
        return {k: (bool(v) if k == "constant" else int(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> TermSpace:
        """Inverse of :meth:`to_dict`."""
        return cls(**{k: data[k] for k in ("ny", "nu", "degree", "delay", "constant")})

    def coefficient_factors(self, u_scale: float, y_scale: float) -> np.ndarray:
        """Per-term factors from scaled-data coefficients to the user's units, (n_terms,).

        The coefficients were fitted on ``u / u_scale`` and ``y / y_scale``.

        A term with ``a`` output and ``b`` input factors has coefficient
        ``theta = theta_scaled * y_scale**(1 - a) * u_scale**(-b)``; with powers of
        two the factors are exact (computed as ``ldexp``, no overflow on the way).
        """
        ey, eu = np.frexp(y_scale)[1] - 1, np.frexp(u_scale)[1] - 1
        lin = self.linear
        out = np.empty(self.n_terms)
        for j, term in enumerate(self.terms):
            a = sum(1 for i in term if lin[i][0] == "y")
            b = len(term) - a
            out[j] = np.ldexp(1.0, int(ey * (1 - a) - eu * b))
        return out

    # -- the regression matrix -------------------------------------------------------
    def lagged(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Matrix of the linear terms, shape ``(N, ny + nu)``, rows t = max_lag..len-1."""
        u = np.asarray(u, dtype=float)
        y = np.asarray(y, dtype=float)
        start, stop = self.max_lag, len(y)
        cols = []
        for sig, lag in self.linear:
            src = y if sig == "y" else u
            cols.append(src[start - lag : stop - lag])
        if not cols:
            return np.empty((stop - start, 0))
        return np.column_stack(cols)

    def regression_matrix(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """All candidate regressors, shape ``(N, n_terms)`` with ``N = len(y) - max_lag``.

        Column ``j`` is term ``j`` of :attr:`terms` evaluated at t = max_lag..len-1.
        Products are built degree by degree from the previous degree's columns, so
        each column costs one vectorised multiplication.
        """
        lin = self.lagged(u, y)
        n_rows, n_lin = lin.shape
        columns: dict[tuple[int, ...], np.ndarray] = {(): np.ones(n_rows)}
        for i in range(n_lin):
            columns[(i,)] = lin[:, i]
        for term in self.terms:
            if len(term) > 1 and term not in columns:
                columns[term] = columns[term[:-1]] * lin[:, term[-1]]
        return np.column_stack([columns[t] for t in self.terms]) if self.terms else np.empty(
            (n_rows, 0)
        )

    def target(self, y: np.ndarray) -> np.ndarray:
        """The regression target y(t) for t = max_lag..len-1."""
        return np.asarray(y, dtype=float)[self.max_lag :]

    def regression(self, u: np.ndarray, y: np.ndarray,
                   segments: list[tuple[int, int]] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Regression matrix and target built inside each segment, stacked.

        ``segments`` are ``[start, stop)`` index ranges of contiguous samples
        (see :mod:`spm_sysid.core.narx.segments`); rows never cross from one segment to
        the next. Segments with no more than ``max_lag`` samples give no row.
        None means the whole record is one segment.
        """
        if segments is None:
            return self.regression_matrix(u, y), self.target(y)
        parts = [(self.regression_matrix(u[a:b], y[a:b]), self.target(y[a:b]))
                 for a, b in segments if b - a > self.max_lag]
        if not parts:
            return np.empty((0, self.n_terms)), np.empty(0)
        return np.vstack([p for p, _ in parts]), np.concatenate([t for _, t in parts])

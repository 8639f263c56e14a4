"""Information criteria that score a model structure (lower is better).

Every criterion sees the same four quantities for a batch of structures:

``sse``   (B,) sum of squared one-step residuals of the least-squares fit;
``n``     number of regression rows N;
``k``     (B,) number of selected terms;
``beta``  (B, n_terms) *standardised* coefficients, zero for unselected terms:
          ``beta_j = theta_j * ||phi_j|| / ||y||`` where ``phi_j`` is the column of
          term j and ``y`` the target. They are dimensionless, so a criterion that
          looks at parameter magnitudes does not depend on the units of u and y.

Built-in criteria are registered by name in :data:`CRITERIA`; a user's own
criterion is any callable ``f(sse, n, k, coefficients) -> float`` on one
structure (``coefficients`` are that structure's standardised coefficients, in
term order), passed where a criterion name is accepted, or registered with
:func:`register_criterion`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: Criteria whose penalty depends on the number of terms only: their optimum over all
#: structures can be certified (:mod:`spm_sysid.core.search.certify`).
CERTIFIABLE = ("aic", "aicc", "bic")

__all__ = [
    "CERTIFIABLE",
    "standardised_value",
    "CRITERIA",
    "Criterion",
    "aic",
    "aicc",
    "bic",
    "get_criterion",
    "make_pmic2",
    "pmic2",
    "register_criterion",
]

VectorFn = Callable[[np.ndarray, int, np.ndarray, "np.ndarray | None"], np.ndarray]


@dataclass(frozen=True)
class Criterion:
    """A named, vectorised structure-selection criterion.

    Parameters
    ----------
    name : str
        Identifier used on the command line, in JSON documents and in the ROS node.
    function : callable
        ``function(sse, n, k, beta) -> scores`` on a batch (see module docstring).
    needs_coefficients : bool
        Whether ``beta`` must be computed (the evaluator skips it otherwise).
    description : str
        One line shown in help texts and reports.
    """

    name: str
    function: VectorFn
    needs_coefficients: bool = False
    description: str = ""

    def __call__(
        self, sse: np.ndarray, n: int, k: np.ndarray, beta: np.ndarray | None = None
    ) -> np.ndarray:
        sse = np.atleast_1d(np.asarray(sse, dtype=float))
        k = np.atleast_1d(np.asarray(k))
        return np.asarray(self.function(sse, n, k, beta), dtype=float)


def _log_mse(sse: np.ndarray, n: int) -> np.ndarray:
    # A perfect fit (sse == 0) would give -inf; clamp at the smallest positive float so
    # scores stay finite and ordered by k.
    return np.log(np.maximum(sse, np.finfo(float).tiny) / n)


def _aic(sse, n, k, beta=None):
    return n * _log_mse(sse, n) + 2.0 * k


def _bic(sse, n, k, beta=None):
    return n * _log_mse(sse, n) + k * np.log(n)


def _aicc(sse, n, k, beta=None):
    # small-sample corrected AIC (Hurvich & Tsai): AIC + 2k(k+1)/(N-k-1); a structure
    # with k >= N - 1 terms has no degrees of freedom left and scores +inf
    k = np.asarray(k, dtype=float)
    room = n - k - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        extra = np.where(room > 0, 2.0 * k * (k + 1.0) / np.where(room > 0, room, 1.0), np.inf)
    return n * _log_mse(sse, n) + 2.0 * k + extra


def make_pmic2(rho: float = 1.0) -> Criterion:
    """Build this project's reconstruction of PMIC2 with magnitude weight ``rho``.

    PMIC2 ("parameter magnitude-based information criterion 2") is cited by the paper
    but its formula is not printed there and could not be found. What this function
    computes is **this project's reconstruction, not the published formula**:

    ``PMIC2 = N ln(SSE/N) + ln(N) * sum_j (1 + rho * ln(1 + 1/|beta_j|))``

    summed over the selected terms, with ``beta_j`` the standardised coefficient
    (see the module docstring). It is BIC plus, per term, an extra penalty that grows
    as the term's standardised parameter magnitude shrinks: a term whose contribution
    to y is tiny must buy its place with a large drop in SSE. ``rho = 0`` gives BIC
    exactly. Values are on the AIC/BIC scale and are not comparable to the paper's
    PMIC2 figures (7.032, 15.583, 21.692). Supply the exact criterion, if you have it,
    as a callable (see :func:`get_criterion`).
    """
    if not rho >= 0:
        raise ValueError(f"rho must be >= 0, got {rho}")

    def _pmic2(sse, n, k, beta):
        mag = np.abs(beta)
        with np.errstate(divide="ignore"):
            extra = rho * np.where(mag > 0, np.log1p(1.0 / np.where(mag > 0, mag, 1.0)), 0.0)
        extra = extra.sum(axis=1)
        # A selected term whose coefficient is exactly zero contributes nothing to the
        # fit: penalise it as infinitely small.
        zero_selected = k - np.count_nonzero(mag, axis=1)
        extra = np.where(zero_selected > 0, np.inf, extra)
        return n * _log_mse(sse, n) + np.log(n) * (k + extra)

    return Criterion(
        name="pmic2",
        function=_pmic2,
        needs_coefficients=True,
        description=(
            "reconstruction: BIC + ln(N)*rho*sum(ln(1 + 1/|standardised coefficient|)), "
            f"rho={rho:g}"
        ),
    )


aic = Criterion("aic", _aic, description="Akaike: N ln(SSE/N) + 2k")
aicc = Criterion("aicc", _aicc, description="Akaike corrected for small samples: "
                 "N ln(SSE/N) + 2k + 2k(k+1)/(N-k-1)")
bic = Criterion("bic", _bic, description="Bayesian: N ln(SSE/N) + k ln N")
pmic2 = make_pmic2()

CRITERIA: dict[str, Criterion] = {c.name: c for c in (aic, aicc, bic, pmic2)}


def register_criterion(criterion: Criterion) -> None:
    """Add a criterion to :data:`CRITERIA` so it can be selected by name."""
    if not isinstance(criterion, Criterion):
        raise TypeError("register_criterion expects a Criterion")
    CRITERIA[criterion.name] = criterion


def _from_scalar(fn: Callable[..., float]) -> Criterion:
    name = getattr(fn, "__name__", "custom")

    def vectorised(sse, n, k, beta):
        return np.array([float(fn(float(s), n, int(kk), b)) for s, kk, b in zip(sse, k, beta)])

    return Criterion(name=name, function=vectorised, needs_coefficients=True,
                     description=f"user callable {name}")


def get_criterion(criterion: str | Criterion | Callable[..., float]) -> Criterion:
    """Resolve a name, a :class:`Criterion` or a user's scalar callable.

    A user callable has the signature ``f(sse, n, k, coefficients) -> float``.
    """
    if isinstance(criterion, Criterion):
        return criterion
    if isinstance(criterion, str):
        try:
            return CRITERIA[criterion.lower()]
        except KeyError:
            raise ValueError(
                f"unknown criterion {criterion!r}; choose one of {sorted(CRITERIA)} "
                "or pass a callable f(sse, n, k, coefficients)"
            ) from None
    if callable(criterion):
        return _from_scalar(criterion)
    raise TypeError(f"criterion must be a name, a Criterion or a callable, got {criterion!r}")


def standardised_value(criterion: Criterion, sse: float, rows: int, k: int,
                       beta: np.ndarray) -> float:
    """The criterion of one structure of ``k`` terms: its SSE, its coefficients standardised.

    ``beta`` (1, n) holds the coefficients scaled as the search scores them (each
    by its column's norm over the target's norm; zeros for terms not in the
    structure, or the structure's own only): criteria that weigh coefficients
    (PMIC2) see the same numbers whatever estimated them. The caller floors the
    SSE as its errors need. Not finite: +inf.
    """
    v = float(criterion(np.array([sse]), rows, np.array([k]),
                        np.atleast_2d(np.asarray(beta, dtype=float)))[0])
    return v if np.isfinite(v) else np.inf

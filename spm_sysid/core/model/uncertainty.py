"""How well each coefficient is determined, and what that means for the model's output.

Least squares (focus prediction): with residual variance
``sigma^2 = SSE / (N - k)``, the coefficients' covariance is
``sigma^2 (A^T A)^-1`` for the selected columns A. It is computed from the
QR factor of A's unit-norm columns on the scaled problem (``A / norms = Q R``,
so ``(A^T A)^-1 = D^-1 R^-1 R^-T D^-1`` with ``D = diag(norms)``), which keeps
it accurate when the columns are nearly collinear, and mapped to the user's
units with the columns' norms in those units.

Simulation focus: the coefficients minimise the free-run error, so the
covariance is the Gauss-Newton one of that problem, ``sigma^2 (J^T J)^-1`` with
J the free-run sensitivities (the Levenberg-Marquardt Jacobian) at the solution
and ``sigma^2`` from the free-run SSE. Free-run errors are correlated in time,
so these intervals are an approximation (too narrow when the errors are
strongly coloured); the document says which method gave them.

Intervals use Student's t with ``N - k`` degrees of freedom. Output bands
(:func:`output_band`) propagate the covariance to predictions and
simulations by Monte Carlo over the coefficients' normal distribution: the
band of each sample is the central ``level`` interval of the outputs of the
draws (draws whose simulation diverged are counted, not used).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from ..defaults import LEVEL
from ..memory import slice_rows

__all__ = ["Band", "Uncertainty", "from_jacobian", "from_least_squares", "output_band",
           "solve_upper", "stacked_factor", "t_quantile"]


#: Degrees of freedom from which :func:`t_quantile` uses its expansion.
T_EXPANSION_DOF = 200


def t_quantile(dof: float, p: float) -> float:
    """Quantile ``p`` of Student's t with ``dof`` degrees of freedom.

    From ``dof >= 200`` (records of a few hundred samples and more) the
    expansion of the t quantile in powers of 1/dof around the normal one
    (Abramowitz and Stegun 26.7.5, four terms): relative error below 1e-10
    there for levels up to 99.9 %, 1e-8 at p = 1 - 1e-8 (a test compares with
    scipy). Fewer degrees of freedom use
    ``scipy.special.stdtrit``, imported then: importing scipy costs a quick
    command 0.1-0.2 s.
    """
    if dof < T_EXPANSION_DOF:
        from scipy.special import stdtrit

        return float(stdtrit(dof, p))
    z = NormalDist().inv_cdf(p)
    z2 = z * z
    g = (z * (z2 + 1) / 4,
         z * ((5 * z2 + 16) * z2 + 3) / 96,
         z * (((3 * z2 + 19) * z2 + 17) * z2 - 15) / 384,
         z * ((((79 * z2 + 776) * z2 + 1482) * z2 - 1920) * z2 - 945) / 92160)
    return float(z + sum(gi / dof ** (i + 1) for i, gi in enumerate(g)))


@dataclass(frozen=True)
class Uncertainty:
    """The covariance of a model's coefficients and how it was obtained.

    Attributes
    ----------
    covariance : ndarray, shape (k, k)
        In the user's units, coefficient order.
    dof : int
        Degrees of freedom of the residual variance, N - k.
    sigma2 : float
        Residual variance (one-step for least squares, free-run for the
        simulation focus).
    method : str
        ``least squares`` or ``free-run Jacobian``.
    """

    covariance: np.ndarray
    dof: int
    sigma2: float
    method: str

    @property
    def standard_errors(self) -> np.ndarray:
        """One per coefficient."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    def standing_for(self, used: int, rows: int | None) -> Uncertainty:
        """The covariance of ``used`` rows (a long record's windows) for ``rows`` in all.

        Times the windows' share, ``dof`` counting every row; itself when ``rows`` is
        None or no more than ``used``.
        """
        if rows is None or rows <= used:
            return self
        k = self.covariance.shape[0]
        return Uncertainty(self.covariance * (used / rows), rows - k, self.sigma2, self.method)

    def intervals(self, coefficients: np.ndarray, level: float = LEVEL) -> np.ndarray:
        """Confidence intervals, shape (k, 2): coefficient -/+ t * standard error."""
        t = t_quantile(max(self.dof, 1), 0.5 + level / 2.0)
        half = t * self.standard_errors
        c = np.asarray(coefficients, dtype=float)
        return np.column_stack([c - half, c + half])

    def spans_zero(self, coefficients: np.ndarray, level: float = LEVEL) -> np.ndarray:
        """Terms whose interval contains 0 (not distinguishable from no term)."""
        iv = self.intervals(coefficients, level)
        return (iv[:, 0] <= 0.0) & (iv[:, 1] >= 0.0)

    def to_dict(self, coefficients: np.ndarray, level: float = LEVEL) -> dict:
        """The document's ``uncertainty`` object (numbers as JSON floats)."""
        iv = self.intervals(coefficients, level)
        return {"method": self.method, "dof": int(self.dof), "sigma2": float(self.sigma2),
                "level": level, "standard_errors": [float(v) for v in self.standard_errors],
                "intervals": [[float(a), float(b)] for a, b in iv],
                "covariance": [[float(v) for v in row] for row in self.covariance]}

    @classmethod
    def from_dict(cls, doc: dict, k: int) -> Uncertainty:
        """Read the document's ``uncertainty`` object (checked; ValueError if malformed)."""
        cov = np.asarray(doc["covariance"], dtype=float)
        if cov.shape != (k, k) or not np.all(np.isfinite(cov)):
            raise ValueError(f"uncertainty.covariance must be a finite {k} x {k} matrix")
        if np.any(np.diag(cov) < 0):
            raise ValueError("uncertainty.covariance has a negative variance on its diagonal "
                             "(not a covariance)")
        if not np.allclose(cov, cov.T, rtol=1e-6, atol=0.0):
            raise ValueError("uncertainty.covariance must be symmetric")
        sigma2 = doc["sigma2"]
        if isinstance(sigma2, bool) or not isinstance(sigma2, (int, float)) or not (
                np.isfinite(sigma2) and sigma2 >= 0):
            raise ValueError("uncertainty.sigma2 must be a finite number >= 0")
        dof = doc["dof"]
        if not isinstance(dof, int) or isinstance(dof, bool) or dof < 0:
            raise ValueError("uncertainty.dof must be an integer >= 0")
        return cls(cov, dof, float(doc["sigma2"]), str(doc["method"]))


def solve_upper(R: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``R^-1 b`` for an upper-triangular R (b a vector or a matrix).

    numpy's LU solve: an upper-triangular matrix is its own LU factor (no row
    is exchanged, every multiplier is 0), so this is back substitution, as
    scipy's ``solve_triangular`` -- without importing scipy's linear algebra
    (about 0.2 s of a quick command). A zero diagonal raises ``LinAlgError``.
    """
    return np.linalg.solve(R, b)


def stacked_factor(blocks: Iterable[np.ndarray], width: int) -> np.ndarray:
    """The triangular factor R of the rows of ``blocks`` stacked (``R^T R = sum B^T B``).

    One block at a time: the QR of the factor so far stacked on the next block,
    so a long matrix given in slices of rows is never held, nor copied, whole.
    """
    r = np.zeros((0, width))
    for block in blocks:
        r = np.linalg.qr(np.vstack([r, block]), mode="r")
    return r


def from_least_squares(r_factor: np.ndarray, column_norms: np.ndarray, sse: float,
                       rows: int) -> Uncertainty:
    """The covariance of a least-squares fit from its QR factor (see the module doc).

    ``r_factor`` is R of the selected columns scaled to unit norm, ``column_norms``
    those columns' norms in the user's units, ``sse`` the SSE in the user's units.
    """
    k = r_factor.shape[0]
    dof = rows - k
    sigma2 = sse / dof if dof > 0 else float("nan")
    rinv = solve_upper(r_factor, np.eye(k))  # R^-1
    scaled = rinv / np.asarray(column_norms, dtype=float)[:, None]  # D^-1 R^-1
    return Uncertainty(sigma2 * scaled @ scaled.T, dof, sigma2, "least squares")


def from_jacobian(jacobian: np.ndarray, sse: float, rows: int | None = None) -> Uncertainty:
    """Gauss-Newton covariance ``sigma^2 (J^T J)^-1`` of a nonlinear least-squares fit.

    ``jacobian`` (rows, k) is d(prediction)/d(coefficient) at the solution, or its
    triangular factor (the same ``J^T J``) with ``rows`` the rows it stands for.
    """
    k = jacobian.shape[1]
    rows = jacobian.shape[0] if rows is None else int(rows)
    dof = rows - k
    sigma2 = sse / dof if dof > 0 else float("nan")
    step = slice_rows(k)  # a long Jacobian's QR without its copy
    r = stacked_factor((jacobian[a:a + step] for a in range(0, jacobian.shape[0], step)), k)
    rinv = solve_upper(r, np.eye(k))
    return Uncertainty(sigma2 * rinv @ rinv.T, dof, sigma2, "free-run Jacobian")


@dataclass(frozen=True)
class Band:
    """A band around a model's output, one value per row of the prediction.

    ``diverged`` is the fraction of coefficient draws whose run left the
    measured range (those draws are not in the band).
    """

    lower: np.ndarray
    upper: np.ndarray
    level: float
    draws: int
    diverged: float

    @property
    def mean_width(self) -> float:
        """Mean width over the rows where the band is defined."""
        w = self.upper - self.lower
        return float(np.nanmean(w)) if np.isfinite(w).any() else float("nan")


def output_band(model, u: np.ndarray, y: np.ndarray, *, horizon: int | None = 1,
                segments=None, level: float = LEVEL, draws: int = 200,
                seed: int = 0) -> Band | None:
    """The ``level`` band of one-step (``horizon=1``), k-step or free-run (None) outputs.

    Monte Carlo over ``draws`` coefficient vectors from the model's normal
    distribution (fixed ``seed``: the same band every time). None when the
    model carries no uncertainty. Memory stays bounded on long records: at most
    :data:`~spm_sysid.core.defaults.BAND_VALUES` simulated values are kept (fewer
    draws, never below :data:`~spm_sysid.core.defaults.MIN_BAND_DRAWS`), and the
    quantiles are taken a block of rows at a time.
    """
    from ..defaults import BAND_VALUES, MIN_BAND_DRAWS

    unc = getattr(model, "uncertainty", None)
    if unc is None:
        return None
    rows = len(y) if segments is None else sum(max(b - a, 0) for a, b in segments)
    draws = int(min(draws, max(MIN_BAND_DRAWS, BAND_VALUES // max(rows, 1))))
    rng = np.random.default_rng(seed)
    cov = 0.5 * (unc.covariance + unc.covariance.T)
    theta = rng.multivariate_normal(model.coefficients, cov, size=draws,
                                     check_valid="ignore", method="eigh")
    lo, hi = 0.5 - level / 2.0, 0.5 + level / 2.0
    if horizon == 1:  # the structure's columns a slice of rows at a time on a long record
        q = np.concatenate([np.empty((2, 0))]
                           + [np.quantile(P[a:a + _BLOCK] @ theta.T, [lo, hi], axis=1)
                              for P, _ in model.regression_slices(u, y, segments)
                              for a in range(0, len(P), _BLOCK)], axis=1)
        return Band(q[0], q[1], level, draws, 0.0)
    if horizon is None and rows * draws > _STRETCH_VALUES:  # the same band, less held
        return _long_free_run_band(model, theta, u, y, segments, (lo, hi), level)
    outputs, ok = None, np.ones(draws, dtype=bool)
    for i, th in enumerate(theta):
        yhat, at = model.with_coefficients(th).run(u, y, horizon, segments)
        if outputs is None:
            outputs = np.empty((len(yhat), draws))
        ok[i] = at is None
        outputs[:, i] = yhat
    if outputs is None or not ok.any():
        n = 0 if outputs is None else len(outputs)
        return Band(np.full(n, np.nan), np.full(n, np.nan), level, draws,
                    float(1.0 - ok.mean()))
    q = np.empty((2, len(outputs)))
    keep = np.flatnonzero(ok)
    for a in range(0, len(outputs), _BLOCK):
        q[:, a:a + _BLOCK] = np.quantile(outputs[a:a + _BLOCK][:, keep], [lo, hi], axis=1)
    return Band(q[0], q[1], level, draws, float(1.0 - ok.mean()))


def _long_free_run_band(model, theta: np.ndarray, u, y, segments, levels, level) -> Band:
    """The free-run band of a record whose draws' runs would pass _STRETCH_VALUES at once.

    Two passes, so memory stays bounded however long the record: each draw's whole
    run decides whether it stays in range (as the one-pass band does) and keeps its
    last simulated outputs before each stretch of rows; then, stretch by stretch, every
    draw that stayed in range is run again from those outputs (a free run depends on
    nothing else: the same values) and the quantiles taken there.
    """
    from .segments import normalise_segments
    from .simulation import divergence_bounds, run_model

    draws, lag = len(theta), model.term_space.max_lag
    u2, y = model.term_space.inputs_2d(u), np.asarray(y, dtype=float)
    step = max(_STRETCH_VALUES // draws, lag + 1)
    stretches, offset = [], 0  # (segment start, first sample, stop, row offset)
    for a, b in normalise_segments(segments, len(y)):
        for s in range(a + lag, b, step):
            stretches.append((a, s, min(s + step, b), offset + s - a - lag))
        offset += max(b - a - lag, 0)
    ok = np.ones(draws, dtype=bool)
    starts = [dict() for _ in range(draws)]  # per draw: first sample -> outputs before it
    for i, th in enumerate(theta):
        yhat, at = model.with_coefficients(th).run(u, y, None, segments)
        ok[i] = at is None
        if ok[i]:
            starts[i] = {s: yhat[o - lag:o].copy() for a, s, _, o in stretches if s > a + lag}
    if not ok.any():
        return Band(np.full(offset, np.nan), np.full(offset, np.nan), level, draws, 1.0)
    bounds = divergence_bounds(y)
    q = np.empty((2, offset))
    for a, s, e, o in stretches:
        values = np.empty((e - s, int(ok.sum())))
        for j, i in enumerate(np.flatnonzero(ok)):
            y_from = y[s - lag:e].copy()
            if s > a + lag:
                y_from[:lag] = starts[i][s]
            values[:, j], _ = run_model(model.compiled, theta[i], u2[s - lag:e], y_from, None,
                                        bounds)
        for c in range(0, e - s, _BLOCK):
            q[:, o + c:o + min(c + _BLOCK, e - s)] = np.quantile(values[c:c + _BLOCK], levels,
                                                                 axis=1)
    return Band(q[0], q[1], level, draws, float(1.0 - ok.mean()))


#: Rows whose quantiles are taken at once (bounds the copies a quantile makes).
_BLOCK = 20_000

#: Simulated values a long record's free-run band holds at once (20 MB): each stretch's
#: runs of every draw (:func:`_long_free_run_band`).
_STRETCH_VALUES = 2_500_000

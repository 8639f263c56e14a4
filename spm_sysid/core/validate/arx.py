"""The yardstick: the linear ARX model a user gets in one line, fitted by least squares.

Every output is regressed on the lags 1..n of every output and of every input
and a constant (delay 1), by plain least squares; the order n is chosen on the
estimation data's own free run (the order whose simulation of those data is
closest), which is what a careful user can know before seeing new data. A
NARX model earns its nonlinear terms only by simulating held-out data better
than this (:mod:`benchmarks.accuracy` measures it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg import scaled_lstsq

__all__ = ["ArxModel", "choose_arx", "fit_arx", "fit_percent", "rmse"]


def _as_2d(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a.reshape(len(a), -1)


def _row(u: np.ndarray, y: np.ndarray, t: int, order: int, constant: bool) -> np.ndarray:
    """The regressors of sample t: y(t-1..t-n) of each output, u(t-1..t-n) of each input, 1."""
    past_y = y[t - order:t][::-1].T.ravel()  # output by output, lag 1 first
    past_u = u[t - order:t][::-1].T.ravel()
    return np.concatenate([past_y, past_u, [1.0] if constant else []])


@dataclass(frozen=True)
class ArxModel:
    """A linear ARX model of order n: ``theta`` maps the regressors to each output.

    Attributes
    ----------
    order : int
    theta : ndarray, shape (regressors, outputs)
        Rows: y_1(t-1..t-n), ..., y_q(t-1..t-n), u_1(t-1..t-n), ..., u_m(t-1..t-n),
        then the constant.
    constant : bool
    """

    order: int
    theta: np.ndarray
    constant: bool = True

    def simulate(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Free run over the record: the first ``order`` samples measured, then fed back.

        Shape (n, outputs); NaN from the first sample that is not finite on.
        """
        u, y = _as_2d(u), _as_2d(y)
        sim = y.copy()
        n = self.order
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging run: NaN
            for t in range(n, len(y)):
                sim[t] = _row(u, sim, t, n, self.constant) @ self.theta
                if not np.all(np.isfinite(sim[t])):
                    sim[t:] = np.nan
                    break
        return sim


def fit_arx(u: np.ndarray, y: np.ndarray, order: int, constant: bool = True) -> ArxModel:
    """Least squares of the order-``order`` ARX model on u, y (rows t = order .. n-1)."""
    u, y = _as_2d(u), _as_2d(y)
    X = np.array([_row(u, y, t, order, constant) for t in range(order, len(y))])
    theta = scaled_lstsq(X, y[order:])
    return ArxModel(order, theta, constant)


def rmse(y: np.ndarray, yhat: np.ndarray, start: int = 0) -> np.ndarray:
    """Root mean squared error per output over samples ``start`` on (inf where NaN)."""
    y, yhat = _as_2d(y)[start:], _as_2d(yhat)[start:]
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.sqrt(np.mean((y - yhat) ** 2, axis=0))
    return np.where(np.isfinite(out), out, np.inf)


def fit_percent(y: np.ndarray, yhat: np.ndarray, start: int = 0) -> np.ndarray:
    """100 (1 - ||y - yhat|| / ||y - mean y||) per output over samples ``start`` on."""
    y, yhat = _as_2d(y)[start:], _as_2d(yhat)[start:]
    out = 100.0 * (1.0 - np.linalg.norm(y - yhat, axis=0)
                   / np.linalg.norm(y - y.mean(axis=0), axis=0))
    return np.where(np.isfinite(out), out, -np.inf)


def choose_arx(u: np.ndarray, y: np.ndarray, orders=range(1, 11),
               constant: bool = True) -> ArxModel:
    """The ARX model whose free run of the same data (u, y) is best (summed RMSE, scaled).

    Each output's RMSE is divided by its standard deviation, so outputs of other
    units weigh alike; a run that diverges is never chosen while another does not.
    """
    y2 = _as_2d(y)
    scale = y2.std(axis=0)
    scale[scale == 0] = 1.0
    start = max(orders)
    best, best_score = None, np.inf
    for n in orders:
        model = fit_arx(u, y, n, constant)
        score = float(np.sum(rmse(y2, model.simulate(u, y2), start) / scale))
        if best is None or score < best_score:
            best, best_score = model, score
    return best

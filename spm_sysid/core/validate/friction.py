"""Does the record show friction? A hint for ``--regressors friction`` before any search.

Coulomb friction is a force of constant size whose sign follows the velocity. A
polynomial can only approximate a sign with odd powers; the friction preset
(:mod:`~spm_sysid.core.model.presets`) adds the sign itself. On a velocity loop
with Coulomb friction every command without the preset was worse than a linear
ARX model, and nothing pointed to the preset.

:func:`friction_sign` is a least-squares test: beside a linear ARX model *with*
the polynomial's own answer to a sign (the last output's square and cube, the
last step's cube, each input's last square and cube), how much of the squared
residual do ``sign(y(t-1)-y(t-2))`` (the sign of a position's velocity) and
``sign(y(t-1))`` (of a velocity itself) remove? The polynomial terms keep odd
nonlinearities that are not friction out: Silverbox's cubic spring reads 8.8 %
with the own sign alone, 0.01 % with them; a plant behind a cubic or a square
root of its input 4.0-11 % without the input's powers (a hint on 5 of 6
records), 1.8-4.7 % with them (none);
velocity loops with Coulomb friction 22-40 % at two lags, 8-24 % at four or
eight (ten records each); the robot arm, the dryer, the heat exchanger, the
Wiener-Hammerstein record and the two tanks at most 0.2 %.

A record sampled far faster than it moves (the data check's
:func:`~.excitation.oversampling`) is read at its rate and at the rate the check
advises, the larger share counting (:func:`strongest_friction_sign`): the step
of a 1 kHz joint's position is mostly measurement noise (0.06-0.5 % at 1 kHz,
5.7-35 % at the advised rate, at two to eight lags), while a 1 kHz velocity loop's own sign reads
22-40 % at its rate and 1.6-5.4 % at a twelfth of it. At the record's rate of an
oversampled record only the own sign is read: there the step's sign is the
measurement noise's, which the lagged outputs' noise correlates with (steps
held 1000 samples at 100x read 23-30 % from it).

numpy only (the data check runs before every search): the p-value is the
large-sample chi-square one (the test needs :data:`FRICTION_MIN_ROWS` rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..linalg import scaled_lstsq
from ..model.presets import arx_columns

__all__ = ["FRICTION_LEVEL", "FRICTION_MIN_ROWS", "FRICTION_ROWS", "FRICTION_SHARE",
           "FrictionSign", "cubic_arx_design", "friction_sign", "strongest_friction_sign"]

#: The hint is given when the signs remove at least this share of the squared residual ...
FRICTION_SHARE = 0.05

#: ... significantly at this level (a column of noise removes a share by chance) ...
FRICTION_LEVEL = 1e-3

#: ... read on at most this many rows (the first of the longest segment: quick on 10^6) ...
FRICTION_ROWS = 50_000

#: ... and on at least this many (below, no hint).
FRICTION_MIN_ROWS = 200

#: An output's own sign is tested when each side holds at least this share of it.
SIDE = 0.05


@dataclass(frozen=True)
class FrictionSign:
    """The test's outcome (:func:`friction_sign`)."""

    share: float          # of the squared residual the signs remove
    p_value: float        # large-sample, chi-square with ``len(signs)`` degrees of freedom
    signs: tuple[str, ...]  # the sign columns tested (texts of the output ``y``)
    every: int            # the test read every ``every``-th sample
    rows: int

    @property
    def shows_friction(self) -> bool:
        return self.share >= FRICTION_SHARE and self.p_value < FRICTION_LEVEL


def friction_sign(y: np.ndarray, u: np.ndarray, ny: int = 2, nu: int = 2, every: int = 1,
                  step_sign: bool = True) -> FrictionSign | None:
    """How much the output's signs explain beside a linear ARX with cubic terms (module doc).

    Parameters
    ----------
    y, u : ndarray
        One contiguous stretch of the output, shape (n,), and the inputs, (n,) or (n, m).
    ny, nu : int
        Output lags (at least 2) and lags of each input of the linear ARX part.
    every : int
        Read every ``every``-th sample (an oversampled record's advised rate).
    step_sign : bool
        Test the step's sign (False: the output's own sign only; None is returned
        when that is not tested either).

    Returns
    -------
    FrictionSign or None
        None when the stretch is too short or a signal is not finite.
    """
    u = np.asarray(u, dtype=float)
    u = u.reshape(len(u), -1)[::every][:FRICTION_ROWS]
    y = np.asarray(y, dtype=float)[::every][:FRICTION_ROWS]
    ny, nu = max(int(ny), 2), max(int(nu), 1)
    n = len(y)
    if n - max(ny, nu) < FRICTION_MIN_ROWS or not (np.all(np.isfinite(y))
                                                   and np.all(np.isfinite(u))):
        return None
    X, target, lag0, _ = cubic_arx_design(y, u, ny, nu)
    X = np.column_stack([X, *_input_powers(u, lag0)])
    last = y[lag0 - 1:n - 1]
    step = last - y[lag0 - 2:n - 2]
    signs, extra = (["sign(y(t-1)-y(t-2))"], [np.sign(step)]) if step_sign else ([], [])
    if min(np.mean(y > 0), np.mean(y < 0)) >= SIDE:
        signs.append("sign(y(t-1))")
        extra.append(np.sign(last))
    if not extra:
        return None
    without, with_signs = _sse(X, target), _sse(np.column_stack([X, *extra]), target)
    dof = len(target) - X.shape[1] - len(extra)
    share = 1.0 - with_signs / without if without > 0 else 0.0
    if share <= 0 or with_signs <= 0:
        p = 1.0 if share <= 0 else 0.0
    else:  # q F is chi-square with q degrees of freedom for many rows
        chi2 = (without - with_signs) / (with_signs / dof)
        p = math.erfc(math.sqrt(chi2 / 2)) if len(extra) == 1 else math.exp(-chi2 / 2)
    return FrictionSign(float(share), float(p), tuple(signs), every, len(target))


def cubic_arx_design(y: np.ndarray, u: np.ndarray, ny: int, nu: int,
                     scales: tuple[float, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, int, tuple[float, float]]:
    """A linear ARX model's columns with the polynomial's answer to an odd force.

    ``ny`` output lags, a constant, ``nu`` lags of each input (columns of ``u``,
    shape (n, m)), and the last output's square and cube and the last step's
    cube, each over a scale: ``scales`` (the last output's, the last step's),
    by default their standard deviations here (powers stay well scaled).
    Returns the (rows, columns) matrix, the target ``y[lag0:]``, ``lag0`` (the
    sample of the first row) and the scales used.
    """
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float).reshape(len(y), -1)
    n = len(y)
    inputs = [(str(j), tuple(range(1, nu + 1)), u[:, j]) for j in range(u.shape[1])]
    cols, lag0 = arx_columns(y, inputs, ny)
    last = y[lag0 - 1:n - 1]
    step = last - y[lag0 - 2:n - 2]
    if scales is None:
        scales = (_scale(last), _scale(step))
    cols += [(last / scales[0]) ** 2, (last / scales[0]) ** 3, (step / scales[1]) ** 3]
    return np.column_stack(cols), y[lag0:], lag0, scales


def strongest_friction_sign(y: np.ndarray, u: np.ndarray, ny: int = 2, nu: int = 2,
                            advised_every: int = 1) -> FrictionSign | None:
    """:func:`friction_sign` at the record's rate and at ``advised_every``: the larger share.

    At the record's rate of an oversampled record (``advised_every`` > 1) the step
    is mostly measurement noise, whose sign the lagged outputs' noise correlates
    with: only the output's own sign is read there (a step test held 2000 samples
    at 100x read 23 % from the noise's steps). None when neither rate has enough
    rows.
    """
    advised = max(int(advised_every), 1)
    found = [r for r in (friction_sign(y, u, ny, nu, k, step_sign=k > 1 or advised == 1)
                         for k in sorted({1, advised})) if r is not None]
    return max(found, key=lambda r: r.share, default=None)


def _input_powers(u: np.ndarray, lag0: int) -> list[np.ndarray]:
    """Each input's last sample squared and cubed (over its deviation).

    An input's own odd nonlinearity (a Hammerstein cubic, a square root) is then not
    read as friction.
    """
    last = u[lag0 - 1:len(u) - 1]
    out = []
    for j in range(last.shape[1]):
        x = last[:, j] / _scale(last[:, j])
        out += [x ** 2, x ** 3]
    return out


def _scale(x: np.ndarray) -> float:
    """The signal's standard deviation, 1 when it is constant."""
    s = float(np.std(x))
    return s if s > 0 else 1.0


def _sse(X: np.ndarray, target: np.ndarray) -> float:
    r = target - X @ scaled_lstsq(X, target)
    return float(r @ r)

"""Named sets of regressors, expanded from the data: ``friction`` and ``saturation``.

A preset is a word a user types (``--regressors friction``) that stands for
regressor expressions of :mod:`.regressors`, with scales and levels read from
the estimation samples:

* ``friction`` -- Coulomb friction is a force of constant size against the
  velocity. For a position output (a joint driven by a torque) the velocity is
  the output's last step: the sign and the absolute value of
  ``y(t-1)-y(t-2)``, and its ``tanh`` over the median absolute step (a smooth
  sign). For an output that is itself a velocity (a velocity loop, a wheel) the
  friction follows the output's own sign: ``sign(y(t-1))`` and its ``tanh``
  are added too when that sign explains at least :data:`OWN_SIGN_SHARE` of the
  residual of a linear ARX model with the last step's sign
  (:func:`own_sign_matters`; velocity loops with Coulomb friction: 9-14 %, and
  the Silverbox oscillator's displacement 8.8 %; two coupled joints' positions
  2.7 % and 0.2 %, a velocity loop with viscous friction 1.0 %, the robot arm's
  acceleration, the Wiener-Hammerstein record and the joint's position below
  0.1 %). Added to every record they would cost the others candidates that
  stand in for one another: the robot arm's certification with the preset went
  from 0.04 s to not certified in 10 s.
* ``saturation`` -- each lag of each input clipped at the level a linear ARX
  prefers (:func:`saturation_level`): an actuator's limit is not among the
  command's own samples.
"""

from __future__ import annotations

import numpy as np

from ..linalg import scaled_lstsq

__all__ = ["OWN_SIGN_SHARE", "PRESETS", "SATURATION_PERCENTILES", "arx_columns", "expand_presets",
           "own_sign_matters", "preset_inputs", "saturation_level"]

#: The words that name a set of regressors.
PRESETS = ("friction", "saturation")

#: Percentiles of an input's magnitude where the ``saturation`` preset looks for its limit.
SATURATION_PERCENTILES = tuple(range(5, 100, 5))

#: ``friction`` adds the output's own sign when it removes at least this share of a
#: linear ARX model's squared residual (a velocity with Coulomb friction).
OWN_SIGN_SHARE = 0.05

#: ... and when each sign holds at least this share of the samples (an output that
#: stays on one side of zero has no sign to read).
OWN_SIGN_SIDE = 0.05

#: ... and when that reduction is significant at this level (an F test: on a short
#: record a column of noise removes 5 % by chance).
OWN_SIGN_LEVEL = 1e-3

Inputs = list[tuple[str, tuple[int, ...], np.ndarray]]


def expand_presets(items: list[str], output: str, y: np.ndarray | None = None,
                   inputs: Inputs | None = None, ny: int = 2,
                   own_sign: bool | None = None) -> list[str]:
    """Regressor texts with presets expanded (their scales and levels from the data).

    Parameters
    ----------
    items : list of str
        Preset names and expressions; expressions pass through unchanged.
    output : str
        The output's name.
    y : ndarray, optional
        The output's estimation samples (``friction`` and ``saturation`` need them).
    inputs : list of (name, lags, samples), optional
        Per input (:func:`preset_inputs`): ``saturation`` clips them, ``friction``'s
        test of the output's own sign regresses on them.
    ny : int
        The output lags of the presets' linear ARX models.
    own_sign : bool, optional
        Whether ``friction`` adds the output's own sign: None decides from the data
        (:func:`own_sign_matters`); False for samples taken around an operating
        point (their sign is not the record's).
    """
    out: list[str] = []
    for item in items:
        name = item.strip()
        if name == "friction":
            if own_sign is None:
                own_sign = own_sign_matters(y, inputs or [], ny)
            out += _friction(output, y, own_sign)
        elif name == "saturation":
            out += _saturation(inputs or [], y, ny)
        else:
            out.append(item)
    return out


def preset_inputs(term_space, u: np.ndarray | None) -> Inputs:
    """(name, lags, samples) of each input of a term space, for :func:`expand_presets`.

    ``u``: the estimation samples, one column per input (None: no input preset).
    """
    if u is None:
        return []
    u = np.asarray(u, dtype=float)
    u = u[:, None] if u.ndim == 1 else u
    return [(name, tuple(lag for src, lag in term_space.linear if src == j), u[:, j])
            for j, name in enumerate(term_space.inputs[:u.shape[1]])]


def _friction(output: str, y: np.ndarray | None, own_sign: bool) -> list[str]:
    step = f"{output}(t-1)-{output}(t-2)"
    scale = 1.0
    if y is not None and len(y) > 2:
        d = np.abs(np.diff(np.asarray(y, dtype=float)))
        d = d[np.isfinite(d) & (d > 0)]
        if d.size:
            scale = float(f"{float(np.median(d)):.3g}")
    texts = [f"sign({step})", f"abs({step})", f"tanh(({step})/{scale!r})"]
    if own_sign:
        texts += [f"sign({output}(t-1))", f"tanh({output}(t-1)/{scale!r})"]
    return texts


def arx_columns(y: np.ndarray, inputs: Inputs, ny: int, skip: int | None = None
                 ) -> tuple[list[np.ndarray], int]:
    """The columns of a linear ARX model of y, and the row they start at.

    Its ``ny`` lags, a constant, and every input's lags but input ``skip``'s.
    """
    lag0 = max([ny] + [max(lags, default=0) for _, lags, _ in inputs])
    n = len(y)
    cols = [y[lag0 - k:n - k] for k in range(1, ny + 1)] + [np.ones(n - lag0)]
    cols += [np.asarray(x, dtype=float)[lag0 - lag:n - lag] for i, (_, lags, x)
             in enumerate(inputs) if i != skip for lag in lags]
    return cols, lag0


def own_sign_matters(y: np.ndarray | None, inputs: Inputs, ny: int) -> bool:
    """Whether the output's own sign is a friction term: it explains the ARX's residual.

    True when each sign holds at least :data:`OWN_SIGN_SIDE` of the samples and
    ``sign(y(t-1))`` beside a linear ARX model and the last step's sign (``ny``
    output lags, at least 2, every input's lags, a constant,
    ``sign(y(t-1)-y(t-2))``; least squares) removes at least
    :data:`OWN_SIGN_SHARE` of its squared residual, significantly
    (:data:`OWN_SIGN_LEVEL`, scipy's F distribution): the output's own sign says
    what its last step's does not.
    """
    from scipy.stats import f as f_distribution

    if y is None:
        return False
    y = np.asarray(y, dtype=float)
    finite = y[np.isfinite(y)]
    if not finite.size or min(np.mean(finite > 0), np.mean(finite < 0)) < OWN_SIGN_SIDE:
        return False
    cols, lag0 = arx_columns(y, inputs, max(int(ny), 2))
    if len(y) - lag0 < 4 * (len(cols) + 2):
        return False
    step = np.sign(y[lag0 - 1:-1] - y[lag0 - 2:-2])  # the position's friction, beside
    X = np.column_stack(cols + [step, np.sign(y[lag0 - 1:-1])])
    target = y[lag0:]
    ok = np.isfinite(target) & np.all(np.isfinite(X), axis=1)
    X, target = X[ok], target[ok]

    def sse(A: np.ndarray) -> float:
        r = target - A @ scaled_lstsq(A, target)
        return float(r @ r)

    without, dof = sse(X[:, :-1]), len(target) - X.shape[1]
    with_sign = sse(X)
    if not (without > 0 and with_sign <= (1.0 - OWN_SIGN_SHARE) * without and dof > 0):
        return False
    statistic = (without - with_sign) / max(with_sign / dof, np.finfo(float).tiny)
    return bool(f_distribution.sf(statistic, 1, dof) < OWN_SIGN_LEVEL)


def _saturation(inputs: Inputs, y: np.ndarray | None, ny: int) -> list[str]:
    out: list[str] = []
    for j, (name, lags, _) in enumerate(inputs):
        level = saturation_level(y, inputs, j, ny)
        if level is not None:
            out += [f"sat({name}(t-{lag}),{level!r})" if lag else f"sat({name}(t),{level!r})"
                    for lag in lags]
    return out


def saturation_level(y: np.ndarray | None, inputs: Inputs, j: int, ny: int) -> float | None:
    """The level at which input j is clipped best: a linear ARX's error profiled over it.

    The ARX regresses y(t) on its ``ny`` lags, every input's lags and a constant,
    input j clipped at the level; the level runs over the 5th..95th percentiles
    of |u_j| (:data:`SATURATION_PERCENTILES`), then is refined between the best
    one's neighbours (scipy's bounded scalar search), 3 digits. None: an input
    that is always zero, or too few samples.
    """
    from scipy.optimize import minimize_scalar

    u_j = np.asarray(inputs[j][2], dtype=float)
    size = np.abs(u_j[np.isfinite(u_j)])
    size = size[size > 0]
    lag0 = max([ny] + [max(lags, default=0) for _, lags, _ in inputs])
    if y is None or not size.size or len(y) - lag0 < 4 * (ny + 2):
        return None
    y = np.asarray(y, dtype=float)
    n = len(y)
    fixed, _ = arx_columns(y, inputs, ny, skip=j)
    lagged = [u_j[lag0 - lag:n - lag] for lag in inputs[j][1]]
    target = y[lag0:]
    ok = np.isfinite(target) & np.all(np.isfinite(np.column_stack(fixed + lagged)), axis=1)

    def sse(level: float) -> float:
        X = np.column_stack(fixed + [np.clip(x, -level, level) for x in lagged])[ok]
        r = target[ok] - X @ scaled_lstsq(X, target[ok])
        return float(r @ r)

    grid = np.percentile(size, SATURATION_PERCENTILES)
    best = int(np.argmin([sse(level) for level in grid]))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    level = minimize_scalar(sse, bounds=(lo, hi), method="bounded").x if hi > lo else lo
    return float(f"{float(level):.3g}")

"""Plain least squares whose answer does not depend on the signals' units.

numpy's cut-off of small singular values is relative to the largest; columns of
very different sizes (an input in units of 1e5, an output in units of 1e-7: a
record in pascals and metres) then lose the small ones, and a check built on the
fit answers differently for the same record in other units: the friction check
warned on a second-order plant written in such units and not on the same plant
in volts, and the linear ARX comparator chose another order. The data checks,
the presets' scales, the linear ARX and the coupled model's direct fit use this.
"""

from __future__ import annotations

import numpy as np

__all__ = ["column_scales", "scaled_lstsq"]


def column_scales(X: np.ndarray) -> np.ndarray:
    """Each column's norm (1 for a zero column): dividing by it gives unit-norm columns."""
    norms = np.linalg.norm(X, axis=0)
    return np.where(norms > 0, norms, 1.0)


def scaled_lstsq(X: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least squares of ``target`` on X's columns, each scaled to unit norm first.

    The coefficients are in X's units; a zero column gets a zero coefficient.
    """
    norms = column_scales(X)
    theta = np.linalg.lstsq(X / norms, target, rcond=None)[0]
    return theta / (norms[:, None] if theta.ndim == 2 else norms)

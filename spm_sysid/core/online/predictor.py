"""One-step prediction of a NARX model, one sample at a time.

:class:`OnlinePredictor` keeps the last ``max_lag`` samples of every signal in
a ring and, for each new sample, computes the model's regressors (the selected
terms) and the one-step prediction of the output -- the same numbers as
:meth:`NarxModel.predict` on the whole record (a test checks it), at a few
microseconds per sample. A gap in the stream (:meth:`reset`) starts the
history again, as regression rows never cross a gap offline.
"""

from __future__ import annotations

import numpy as np

from ..model.narx import NarxModel

__all__ = ["OnlinePredictor"]


class OnlinePredictor:
    """The model's regressors and one-step prediction for each new sample.

    Parameters
    ----------
    model : NarxModel
        Its term space gives the lags; its coefficients the prediction (replace
        them with :meth:`set_coefficients`, e.g. by a tracker's).
    """

    def __init__(self, model: NarxModel) -> None:
        space = model.term_space
        self.n_inputs = space.n_inputs
        self.max_lag = space.max_lag
        self._len = self.max_lag + 1
        # history: row 0 the output, rows 1.. the inputs; column = time modulo _len
        self._hist = np.zeros((1 + self.n_inputs, self._len))
        lin = space.linear
        self._src = np.array([s + 1 for s, _ in lin], dtype=np.intp)
        self._lag = np.array([lag for _, lag in lin], dtype=np.intp)
        # each selected term as indices into [linear values..., 1.0], padded with the 1.0
        terms = [space.terms[i] for i in model.term_indices]
        width = max((len(t) for t in terms), default=1) or 1
        one = space.n_bases  # the constant 1, after the regressors if any
        self._factors = np.full((len(terms), width), one, dtype=np.intp)
        for r, t in enumerate(terms):
            self._factors[r, :len(t)] = t
        self._space = space
        self._lin = np.ones(one + 1)
        self.coefficients = np.asarray(model.coefficients, dtype=float).copy()
        self.reset()

    def reset(self) -> None:
        """Forget the history (after a gap): predictions resume ``max_lag`` samples later."""
        self._t = 0

    @property
    def ready(self) -> bool:
        """The history holds enough samples for the next prediction."""
        return self._t >= self.max_lag

    def set_coefficients(self, coefficients: np.ndarray) -> None:
        self.coefficients = np.asarray(coefficients, dtype=float).copy()

    def regressors(self, u) -> np.ndarray | None:
        """The selected terms at the current time t from u(t) and the history.

        None until ``max_lag`` samples have been seen. Call before :meth:`push`
        of the same sample.
        """
        if not self.ready:
            return None
        col = self._t % self._len
        self._hist[1:, col] = u  # u(t) (delay 0 terms use it); y(t) is not used
        n_lin = len(self._src)
        self._lin[:n_lin] = self._hist[self._src, (col - self._lag) % self._len]
        if self._space.regressors:
            self._lin[n_lin:-1] = self._regressor_values(col)
        return np.prod(self._lin[self._factors], axis=1)

    def _regressor_values(self, col: int) -> np.ndarray:
        """Each regressor at the current time from the history (the term space's rule)."""
        from ..model.regressors import evaluate

        space = self._space
        rows = {name: 1 + i for i, name in enumerate(space.inputs)}
        rows[space.output] = 0

        def get(name: str, lag: int) -> float:
            return self._hist[rows[name], (col - lag) % self._len]

        return np.array([float(evaluate(e, get)) for e in space.regressor_exprs])

    def push(self, u, y: float) -> None:
        """Add the sample (u(t), y(t)) to the history."""
        col = self._t % self._len
        self._hist[0, col] = y
        self._hist[1:, col] = u
        self._t += 1

    def step(self, u, y: float) -> tuple[float, np.ndarray] | None:
        """One-step prediction of y(t) and the regressors; then the sample is added.

        None (and the sample added) while the history is too short.
        """
        phi = self.regressors(u)
        self.push(u, y)
        if phi is None:
            return None
        return float(phi @ self.coefficients), phi

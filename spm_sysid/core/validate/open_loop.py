"""Is the system stable in open loop? Free-run comparison only means something if it is.

A system that is unstable in open loop (a ball on a beam) cannot be simulated
for long by *any* model: a small error in the coefficients or in the initial
state makes the free run grow away from the record, so free-run errors compare
divergences, not models. Such records are judged on the k-step-ahead
prediction instead (:data:`HORIZON` steps unless the job asks for another
horizon). A system that integrates (a position driven by a torque, a tank level
fed by a flow) drifts too, but more slowly, and its free run is what users
compare: it is judged on its free run.

The check fits the linear ARX model of the term space's output order (least
squares on every segment's rows, with a constant) and looks at the roots of
its autoregressive polynomial:

* **integrating** -- a real positive pole (angle below :data:`REAL_ANGLE`) whose
  time constant ``1 / (1 - |p|)`` is longer than half the record
  (``|p| >= 1 - 2 / N``), up to ``1 +`` :data:`INTEGRATOR_MARGIN` (least squares
  puts a drive's integrator a little beyond 1). Its free run is still what
  users compare (benchmarks of positioning drives are free-run errors), so it
  is judged on its free run (:meth:`OpenLoop.note`);
* **unstable** -- any other pole with ``|p| > 1 + 2 / N``, read again at the
  next orders (:func:`open_loop_check`): judged on the k-step prediction;
* **stable** otherwise. A lightly damped resonance (a complex pair close to the
  unit circle, as the flexible robot arm has) is stable: its free run is
  meaningful.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import (
    DEPENDENT,
    HORIZON,
    INTEGRATOR_MARGIN,
    OPEN_LOOP_CONFIRM,
    REAL_ANGLE,
    STRUCTURE_SLICE_BYTES,
)
from ..model.uncertainty import stacked_factor

__all__ = ["HORIZON", "OpenLoop", "REAL_ANGLE", "independent_columns", "open_loop_check"]


@dataclass(frozen=True)
class OpenLoop:
    """The verdict of :func:`open_loop_check`.

    Attributes
    ----------
    kind : str
        ``"stable"``, ``"integrating"`` or ``"unstable"``.
    pole : complex
        The deciding pole (the largest in magnitude when stable).
    order : int
        Order of the linear ARX model the poles come from.
    rows : int
        Rows it was fitted on.
    """

    kind: str
    pole: complex
    order: int
    rows: int

    @property
    def free_run_applies(self) -> bool:
        """Free runs compare models: a stable or integrating output (not an unstable one)."""
        return self.kind != "unstable"

    def note(self) -> str:
        """For an integrating output: how its free run is judged ('' otherwise)."""
        if self.kind != "integrating":
            return ""
        return (f"the output integrates (a real pole at {self.pole.real:.4f} in the linear ARX "
                f"model of order {self.order}, {self.rows} rows): judged on its free run, as "
                "benchmarks of drives are; its free run drifts with any error of the model, so "
                "compare its free-run error with the linear ARX's (the selection's account "
                "gives both on the same held-out blocks)")

    def reason(self) -> str:
        """Why free-run comparison does not apply ('' when it does)."""
        if self.free_run_applies:
            return ""
        p = self.pole
        where = (f"{p.real:.4f}" if abs(p.imag) < 1e-12
                 else f"{abs(p):.4f} at angle {abs(np.angle(p)):.3f} rad")
        what = ("integrates (a real pole at" if self.kind == "integrating"
                else "is unstable in open loop (a pole of magnitude")
        return (f"the output {what} {where} in the linear ARX model of order {self.order}, "
                f"{self.rows} rows): the free run of any model drifts away from the record, "
                "so free-run errors do not compare models; judged on the k-step prediction "
                "instead")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "pole": [float(self.pole.real), float(self.pole.imag)],
                "magnitude": float(abs(self.pole)), "order": self.order, "rows": self.rows,
                "free_run_applies": self.free_run_applies,
                **({"reason": self.reason()} if not self.free_run_applies else {}),
                **({"note": self.note()} if self.note() else {})}



def independent_columns(X: np.ndarray) -> np.ndarray:
    """The columns of X (unit norm) that the columns before them do not explain, in order.

    The output's lags come first, so an input that repeats the output (``u == y``,
    an output that is twice another) is dropped, not the output's own lags: the
    poles are then the output's, not a split of one signal's coefficients between
    two names (which reads as a pole beyond 1 for a stable record).
    """
    r = np.linalg.qr(X, mode="r")  # numpy's: scipy.linalg costs a command 0.1-0.2 s to import
    diag = np.abs(np.diag(r))
    return np.flatnonzero(diag > DEPENDENT * max(float(diag.max(initial=0.0)), 1.0))


def _arx_slices(u: np.ndarray, y: np.ndarray, segments, n: int, step: int):
    """(regressors, targets) of the order-n ARX model, ``step`` rows at most at a time.

    Rows y(t-1..t-n), u_j(t-1..t-n) of each input, 1; no row crosses a segment's border.
    """
    for a, b in segments:
        for s in range(a + n, b, step):
            idx = np.arange(s, min(s + step, b))
            lagged = [y[idx - k] for k in range(1, n + 1)]
            lagged += [u[idx - k, j] for j in range(u.shape[1]) for k in range(1, n + 1)]
            yield np.column_stack(lagged + [np.ones(len(idx))]), y[idx]


def _arx_fit(u: np.ndarray, y: np.ndarray, segments, n: int
             ) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Least squares of the ARX model on the independent columns: (theta, scale, rows).

    ``theta`` is of the columns scaled by ``scale`` (unit norm). A long record is
    read in slices (:data:`~spm_sysid.core.defaults.STRUCTURE_SLICE_BYTES`): the
    triangular factor of the scaled ``[X t]`` is updated slice by slice and the fit
    on the independent columns solved from it, so no copy of X is held (10^6
    rows held five); a record of one slice takes the one-pass route, unchanged.
    None: too few rows, or a value that is not finite.
    """
    width = n * (1 + u.shape[1]) + 1
    step = max(width + 1, STRUCTURE_SLICE_BYTES // (8 * (width + 1)))
    count = sum(max(b - a - n, 0) for a, b in segments)
    if count <= width:
        return None
    if count <= step:  # one pass
        X, t = (np.concatenate(p) for p in zip(*_arx_slices(u, y, segments, n, step)))
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(t))):
            return None
        scale = np.linalg.norm(X, axis=0)
        scale[scale == 0] = 1.0
        keep = independent_columns(X / scale)
        theta = np.zeros(X.shape[1])
        theta[keep], *_ = np.linalg.lstsq(X[:, keep] / scale[keep], t, rcond=None)
        return theta, scale, count
    squares = np.zeros(width)
    for X, t in _arx_slices(u, y, segments, n, step):
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(t))):
            return None
        squares += np.add.reduce(X * X, axis=0)
    scale = np.sqrt(squares)
    scale[scale == 0] = 1.0
    r = stacked_factor((np.column_stack([X / scale, t])
                        for X, t in _arx_slices(u, y, segments, n, step)), width + 1)
    diag = np.abs(np.diag(r[:width, :width]))
    keep = np.flatnonzero(diag > DEPENDENT * max(float(diag.max(initial=0.0)), 1.0))
    q, rk = np.linalg.qr(r[:width, keep])  # X[:, keep] = Q r[:, keep]: its own QR from there
    theta = np.zeros(width)
    theta[keep] = np.linalg.solve(rk, q.T @ r[:width, width])
    return theta, scale, count


def open_loop_check(u: np.ndarray, y: np.ndarray, segments: list[tuple[int, int]],
                    order: int) -> OpenLoop | None:
    """The open-loop verdict of the record (None when too short to fit the ARX model).

    An "unstable" reading at ``order`` is confirmed at the next
    :data:`~spm_sysid.core.defaults.OPEN_LOOP_CONFIRM` orders: a model of a higher
    order fits the record at least as well, so when one of them reads stable (or
    integrating) the record does not show an instability, and that verdict is
    returned. A real instability reads the same pole at every order; a spurious
    one is a least-squares accident of one order (the robot arm's order-6 ARX puts
    a pole at 1.0071, its orders 7 to 10 none beyond 0.999).

    Parameters
    ----------
    u : ndarray, shape (n,) or (n, inputs)
        The inputs.
    y : ndarray, shape (n,)
        The output.
    segments : list of (start, stop)
        No row crosses a segment's border.
    order : int
        Output and input lags of the ARX model (at least 1).
    """
    u = np.asarray(u, dtype=float).reshape(len(u), -1)
    y = np.asarray(y, dtype=float)
    n = max(int(order), 1)
    verdict = _verdict(u, y, segments, n)
    if verdict is None or verdict.kind != "unstable":
        return verdict
    for higher in range(n + 1, n + 1 + OPEN_LOOP_CONFIRM):
        other = _verdict(u, y, segments, higher)
        if other is None:  # too short for the higher order: the reading stands
            break
        if other.kind != "unstable":
            return other
    return verdict


def _verdict(u: np.ndarray, y: np.ndarray, segments, n: int) -> OpenLoop | None:
    """The verdict of the order-n ARX model's poles alone (see the module)."""
    fit = _arx_fit(u, y, segments, n)
    if fit is None:
        return None
    theta, scale, count = fit
    a_coef = theta[:n] / scale[:n]
    poles = np.roots(np.r_[1.0, -a_coef])
    if not len(poles):
        return OpenLoop("stable", 0j, n, count)
    real = poles[(np.abs(np.angle(poles)) < REAL_ANGLE)]
    if real.size and np.max(np.abs(real)) >= 1.0 - 2.0 / count:
        p = complex(real[np.argmax(np.abs(real))])
        if abs(p) <= 1.0 + max(2.0 / count, INTEGRATOR_MARGIN):
            return OpenLoop("integrating", complex(p.real, 0.0), n, count)
    worst = complex(poles[np.argmax(np.abs(poles))])
    if abs(worst) > 1.0 + 2.0 / count:
        return OpenLoop("unstable", worst, n, count)
    return OpenLoop("stable", worst, n, count)

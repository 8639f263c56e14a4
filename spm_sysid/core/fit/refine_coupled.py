"""Simulation focus for several outputs: all outputs' coefficients refined together.

The structures stay those selected per output; their coefficients are refined
**jointly** (Levenberg-Marquardt over all outputs' coefficients at once) on the
coupled free-run error (:mod:`spm_sysid.core.model.coupled`), each output's
error over its standard deviation so that outputs of different units weigh
alike. A refinement that does not lower that error, or diverges, is not taken.

Levenberg-Marquardt steps only along the directions the record identifies:
those of the start's Jacobian that are well conditioned or along which its
residuals are significant (:data:`~spm_sysid.core.defaults.JOINT_RCOND`,
:data:`~spm_sysid.core.defaults.JOINT_SIGNIFICANCE`). On a record whose
inputs excite few of their lags, free steps lowered the training error along
directions the record hardly sees and grew the two-link arm's held-out errors
2-8x.

Each evaluation is one compiled coupled run with its sensitivities
(:func:`~spm_sysid.core.model.coupled.coupled_sensitivities`): residuals and
Jacobian together, for the project's Levenberg-Marquardt
(:func:`~spm_sysid.core.fit.levenberg.levenberg_marquardt`, MINPACK's rules).
Finite differences cost one coupled run per coefficient per step (on the
two-link arm, 49 runs a step: 70 % of its job). Structures with regressors,
whose coupled run carries no derivatives, are still refined that way (scipy's
MINPACK), in all directions, while a step's runs stay within
:data:`~spm_sysid.core.defaults.JOINT_DIFFERENCE_SAMPLES` simulated samples: six
coupled joints with the friction preset (240 coefficients, 4·10^4 samples) spent
over ten minutes on the first of seven finalists' folds; beyond it each output's
own refinement is kept and the answer says so.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..defaults import JOINT_DIFFERENCE_SAMPLES, JOINT_RCOND, JOINT_SIGNIFICANCE
from ..model.coupled import CoupledCompiled, coupled_run, coupled_sensitivities
from ..model.simulation import divergence_bounds
from ..model.uncertainty import from_jacobian
from .levenberg import levenberg_marquardt

__all__ = ["refine_coupled"]


def refine_coupled(model, u: np.ndarray, Y: np.ndarray,
                   segments: list[tuple[int, int]] | None = None,
                   max_evaluations: int = 100, rows: int | None = None):
    """All outputs' coefficients refined together on the coupled free-run error.

    Parameters
    ----------
    model : MimoModel
        The structures and the starting coefficients.
    u, Y : ndarray
        The estimation record(s).
    segments : list of (start, stop), optional
        Contiguous parts, each simulated from its own start (None: the whole record).
    max_evaluations : int
        Most evaluations of Levenberg-Marquardt (each a coupled run with its
        sensitivities; with regressors, a finite-difference Jacobian costs
        one more run per coefficient besides).
    rows : int, optional
        The rows of each output the covariance stands for when ``segments`` are
        windows of a long record: the windows' covariance is scaled by their
        share of them, and ``dof`` counts them
        (:func:`~spm_sysid.core.fit.refine.free_run_uncertainty`'s rule).

    Returns
    -------
    model : MimoModel
        With the refined coefficients (and their free-run Jacobian uncertainty),
        or the model given when refinement did not help.
    info : dict
        ``before``/``after`` (normalised coupled free-run SSE), ``evaluations``,
        ``taken`` and a ``message``.
    """
    run = _CoupledResiduals(model, u, Y, segments)
    theta0 = np.concatenate([np.asarray(m.coefficients, dtype=float) for m in model.models])
    r0 = run.residuals(theta0)
    before = float(r0 @ r0)
    info = {"before": before, "after": before, "evaluations": 1, "taken": False}
    if run.measured.size <= theta0.size:
        info["message"] = "too few rows to refine"
        return model, info
    if beyond := run.beyond_budget(theta0.size):
        info["message"] = beyond
        return model, info
    try:
        x, evaluations, message, jac = run.solve(theta0, max_evaluations)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:  # pragma: no cover
        info["message"] = f"refinement failed ({exc})"
        return model, info
    sim, div = run.simulate(x)
    r = run.scaled(sim)
    after = float(r @ r)
    info.update(after=after, evaluations=evaluations)
    if div or not after < before:
        info["message"] = ("the refined coefficients diverge" if div else
                           "the coefficients given simulate best together; kept")
        return model, info
    info.update(taken=True, message=message)
    if rows is not None and rows > len(run.measured):
        info["uncertainty_rows"] = len(run.measured)
    return replace(model, models=run.refined_models(model, x, jac, sim, rows)), info


class _CoupledResiduals:
    """The coupled free run of all outputs over the segments, and its scaled residuals.

    Residuals are divided by each output's spread; a sample past a divergence
    costs ten times its output's range (and has no gradient).
    """

    def __init__(self, model, u: np.ndarray, Y: np.ndarray,
                 segments: list[tuple[int, int]] | None) -> None:
        u = np.asarray(u, dtype=float)
        self.u = u[:, None] if u.ndim == 1 else u
        self.Y = np.asarray(Y, dtype=float)
        self.q = q = self.Y.shape[1]
        self.cc = CoupledCompiled.from_models(model.models, self.u.shape[1])
        self.exact = self.cc.program.start.shape[1] == 1  # no regressors
        lag = self.cc.max_lag
        self.segs = [(a, b) for a, b in (segments or [(0, len(self.Y))]) if b - a > lag]
        self.bounds = [divergence_bounds(self.Y[:, i]) for i in range(q)]
        self.scale = np.array([float(np.std(self.Y[:, i])) or 1.0 for i in range(q)])
        self.measured = np.concatenate([self.Y[a + lag:b] for a, b in self.segs])  # (rows, q)
        self.sizes = np.cumsum((0,) + self.cc.n_terms)
        self.penalty = 10.0 * np.array([(hi - lo) for lo, hi in self.bounds]) / self.scale

    def beyond_budget(self, coefficients: int) -> str | None:
        """Why a finite-difference refinement would cost too much (None: it would not)."""
        work = (coefficients + 1) * self.measured.size
        if self.exact or work <= JOINT_DIFFERENCE_SAMPLES:
            return None
        return (f"not refined jointly: with regressors each of the {coefficients} coefficients "
                f"costs a coupled run of {self.measured.size} samples per step ({work:.2g} in "
                f"all, more than {JOINT_DIFFERENCE_SAMPLES:.2g}); each output's own refinement "
                "kept")

    def split(self, theta: np.ndarray) -> list[np.ndarray]:
        """Each output's coefficients."""
        return [theta[self.sizes[i]:self.sizes[i + 1]] for i in range(self.q)]

    def simulate(self, theta: np.ndarray) -> tuple[np.ndarray, bool]:
        """The coupled free run over every segment, and whether any output diverged."""
        runs, diverged = [], False
        for a, b in self.segs:
            sim, div = coupled_run(self.cc, self.split(theta), self.u[a:b], self.Y[a:b],
                                   self.bounds)
            runs.append(sim)
            diverged |= any(d is not None for d in div)
        return np.concatenate(runs), diverged

    def scaled(self, sim: np.ndarray) -> np.ndarray:
        """The residuals of a run over the segments: scaled, a penalty past a divergence."""
        r = (self.measured - sim) / self.scale
        return np.where(np.isfinite(r), r, self.penalty).ravel()

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Scaled free-run residuals of all outputs, one vector (sample by sample)."""
        return self.scaled(self.simulate(theta)[0])

    def evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The residuals and their Jacobian, from the coupled sensitivities.

        Several segments (a long record's windows) are copied into one Jacobian
        as each is computed, not gathered and then concatenated (twice the memory).
        """
        sims, jac, at = [], None, 0
        for a, b in self.segs:
            sim, sens, _ = coupled_sensitivities(self.cc, self.split(theta), self.u[a:b],
                                                 self.Y[a:b], self.bounds)
            sims.append(sim)
            sens /= -self.scale[:, None]  # in place: a Jacobian is rows x outputs x terms
            part = sens.reshape(-1, len(theta))
            if len(self.segs) == 1:
                jac = part  # no copy
            else:
                if jac is None:
                    jac = np.empty((self.measured.size, len(theta)))
                jac[at:at + len(part)] = part
                at += len(part)
        return self.scaled(np.concatenate(sims)), jac

    def solve(self, theta0: np.ndarray, max_evaluations: int
              ) -> tuple[np.ndarray, int, str, np.ndarray | None]:
        """Levenberg-Marquardt from theta0: the end, evaluations, message, Jacobian there.

        The Jacobian is None where the sensitivities give it on demand.
        """
        if self.exact:
            r0, jac0 = self.evaluate(theta0)
            basis = self.identified_directions(r0, jac0)
            first = [(r0, jac0 @ basis)]  # the solver's first evaluation is at theta0

            def evaluate(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                if first:
                    return first.pop()
                r, jac = self.evaluate(theta0 + basis @ z)
                return r, jac @ basis

            sol = levenberg_marquardt(evaluate, np.zeros(basis.shape[1]), max_evaluations)
            return theta0 + basis @ sol.x, sol.nfev, sol.message, None
        from scipy.optimize import least_squares  # imported when a refinement runs

        sol = least_squares(self.residuals, theta0, method="lm", x_scale="jac",
                            max_nfev=max_evaluations)
        return sol.x, int(sol.nfev), str(sol.message), sol.jac

    @staticmethod
    def identified_directions(r: np.ndarray, jac: np.ndarray) -> np.ndarray:
        """The directions of coefficient space the record identifies, as columns.

        ``r`` and ``jac``: the residuals and Jacobian at the start. The right
        singular vectors of the start's Jacobian (columns scaled to unit
        norm) that the record sees well (singular value at least
        :data:`JOINT_RCOND` times the largest) or along which the start's
        residuals call for a step: the Gauss-Newton step's component along vector
        i is ``u_i . r / s_i``, its noise ``sigma / s_i`` (white residuals of the
        start's spread); kept when ``|u_i . r|`` exceeds
        :data:`JOINT_SIGNIFICANCE` ``sigma``. Mapped back to unscaled
        coefficients: a step is ``basis @ z``. From the eigenvectors of the
        scaled ``J'J`` (coefficients by coefficients), not an SVD of ``J`` (rows
        by coefficients: another Jacobian's memory on a long record).
        """
        k = jac.shape[1]
        if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(r))):
            return np.eye(k)  # the solver stops at such a start, and says why
        gram = jac.T @ jac  # scaled below, without a scaled copy of the Jacobian
        norms = np.sqrt(np.diag(gram).copy())
        norms[~(norms > 0)] = 1.0
        power, vectors = np.linalg.eigh(gram / np.outer(norms, norms))
        s = np.sqrt(np.clip(power, 0.0, None))
        if not (s.size and s.max() > 0):  # nothing to step along: the solver says so
            return np.eye(k)
        # u_i . r = v_i . J'r / s_i, where s_i is resolved (above rounding of J'J)
        resolved = s > 1e-6 * s.max()
        along = np.abs(vectors.T @ ((jac.T @ r) / norms)) / np.where(resolved, s, np.inf)
        sigma = np.sqrt(r @ r / max(r.size - s.size, 1))
        keep = (s >= JOINT_RCOND * s.max()) | (along > JOINT_SIGNIFICANCE * sigma)
        return vectors[:, keep] / norms[:, None]

    def refined_models(self, model, theta: np.ndarray, jac: np.ndarray | None,
                       sim: np.ndarray, rows: int | None = None) -> list:
        """Each output's model with its refined coefficients and their uncertainty.

        Each output's uncertainty comes from its rows and columns of the joint
        Jacobian (None: from the sensitivities at theta); scaled to ``rows`` when
        the segments are a long record's windows (see :func:`refine_coupled`).
        """
        jac = self.evaluate(theta)[1] if jac is None else jac
        jac = jac.reshape(len(self.measured), self.q, -1)  # d(r)/d(theta)
        models = []
        for i, (m, th) in enumerate(zip(model.models, self.split(theta))):
            J = -jac[:, i, self.sizes[i]:self.sizes[i + 1]] * self.scale[i]  # d(sim_i)/d(th)
            e = self.measured[:, i] - sim[:, i]
            unc = (from_jacobian(J, float(e @ e)).standing_for(len(J), rows)
                   if np.all(np.isfinite(J)) else m.uncertainty)
            meta = {**m.metadata, "coupled_refinement": True}
            models.append(replace(m, coefficients=np.array(th), uncertainty=unc, metadata=meta))
        return models

"""Several outputs: one coupled NARX model of a multi-joint robot (MIMO).

Each output gets its own structure, selected over a shared kind of candidate
set: the lags of **every** output and every input and their products up to the
degree. It is built on the single-output path: output i's term space has its
own lags ``y_i(t-1..t-ny)`` as the output, and the other outputs as extra
"inputs" with delay 1 and ``ny`` lags (``y_j(t-1..t-ny)``: an output's present
value never enters another output's model, so the model stays causal and can
be simulated). This module is the model; identifying it is the one job of any
number of outputs (:func:`spm_sysid.core.jobs.run_job` on a record of several
outputs, :mod:`spm_sysid.core.jobs.several`): every output gets the whole
single-output path -- GA with SPM, polish, certification, validated selection,
uncertainty -- with its own criterion value; the joint summary is the sum of
the outputs' criterion values (each a log-likelihood-type score of its own
residuals).

The **coupled free-run simulation** (:meth:`MimoModel.simulate`) feeds every
output's prediction back into every term that uses it, all outputs stepping
together; a run that leaves an output's measured range is marked diverged
(per output, from that sample on NaN). With simulation focus the outputs'
coefficients are then refined jointly on that coupled free-run error
(:mod:`spm_sysid.core.model.coupled`).

The document (``spm_sysid/narx-mimo-model``, version 1) holds one
single-output model document (docs/model_format.md) per output; the
single-output document is unchanged and still what one output gives.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..cores import usable_cores
from ..errors import ModelFormatError
from ..files import atomic_write_text, document_json, json_ready
from .metadata import check_mimo_metadata
from .narx import NarxModel, read_json_document
from .terms import TermSpace

__all__ = ["MIMO_SCHEMA", "MimoModel", "augmented_inputs", "in_threads", "output_space",
           "read_model_document"]

MIMO_SCHEMA = "spm_sysid/narx-mimo-model"
MIMO_SCHEMA_VERSION = 1


def output_space(space: TermSpace, outputs: tuple[str, ...], i: int) -> TermSpace:
    """Output ``i``'s term space: its own lags, the inputs', and the other outputs' lags.

    ``space`` gives ny, the inputs (names, nu, delay), degree and constant.
    """
    others = [o for j, o in enumerate(outputs) if j != i]
    nus = tuple(space.nus) + (space.ny,) * len(others)
    delays = tuple(space.delays) + (1,) * len(others)
    return replace(space, output=outputs[i], inputs=tuple(space.inputs) + tuple(others),
                   nu=nus, delay=delays)


def augmented_inputs(u: np.ndarray, Y: np.ndarray, i: int) -> np.ndarray:
    """The inputs of output ``i``'s model: u's columns, then the other outputs'."""
    u = np.asarray(u, dtype=float)
    u = u[:, None] if u.ndim == 1 else u
    others = [j for j in range(Y.shape[1]) if j != i]
    return np.column_stack([u] + [Y[:, j] for j in others])


@dataclass
class MimoModel:
    """One NARX model per output, coupled through the other outputs' lags.

    Attributes
    ----------
    outputs, inputs : tuple of str
    models : list of NarxModel
        Output i's model; its term space's inputs are ``inputs`` then the other
        outputs (:func:`output_space`).
    metadata : dict
    """

    outputs: tuple[str, ...]
    inputs: tuple[str, ...]
    models: list[NarxModel]
    metadata: dict = field(default_factory=dict)

    @classmethod
    def joined(cls, outputs: tuple[str, ...], inputs: tuple[str, ...],
               models: list[NarxModel]) -> MimoModel:
        """The outputs' models as one, with the joint criterion (their values summed)."""
        return cls(tuple(outputs), tuple(inputs), list(models),
                   {"joint_criterion": {"name": models[0].criterion,
                                        "value": float(sum(m.criterion_value for m in models)),
                                        "meaning": "sum of the outputs' values"}})

    @property
    def max_lag(self) -> int:
        return max(m.term_space.max_lag for m in self.models)

    def equations(self) -> list[str]:
        """One equation per output."""
        return [m.equation() for m in self.models]

    # -- running it --------------------------------------------------------------------
    def predict(self, u: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """One-step predictions, shape (n - max_lag, outputs), from measured u and Y."""
        Y = np.asarray(Y, dtype=float)
        lag = self.max_lag
        cols = []
        for i, m in enumerate(self.models):
            p = m.predict(augmented_inputs(u, Y, i), Y[:, i])
            cols.append(p[len(p) - (len(Y) - lag):])
        return np.column_stack(cols)

    def simulate(self, u: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, list[int | None]]:
        """Coupled free-run simulation from the first ``max_lag`` measured samples.

        Returns the simulated outputs for t = max_lag..n-1, shape (n - max_lag,
        outputs), and per output the sample where it left its measured range
        (None when it did not; NaN from there on, and in the outputs that use it).
        Compiled (:func:`spm_sysid.core.model.coupled.coupled_run`).
        """
        from .coupled import CoupledCompiled, coupled_run

        u = np.asarray(u, dtype=float)
        u = u[:, None] if u.ndim == 1 else u
        cc = CoupledCompiled.from_models(self.models, u.shape[1])
        return coupled_run(cc, [m.coefficients for m in self.models], u, Y)

    def k_step(self, u: np.ndarray, Y: np.ndarray, horizon: int
               ) -> tuple[np.ndarray, list[int | None]]:
        """Coupled k-step-ahead predictions, shape (n - max_lag, outputs).

        Row t is every output at t predicted from the measured samples up to
        ``t - horizon`` and the model's own (coupled) outputs in between; the
        first rows, with fewer than ``horizon`` steps of history after the
        start, are predicted from the start (as the free run). Per output, the
        first sample whose prediction left its measured range (None: none).
        """
        from .coupled import CoupledCompiled, coupled_run
        from .simulation import divergence_bounds

        u = np.asarray(u, dtype=float)
        u = u[:, None] if u.ndim == 1 else u
        Y = np.asarray(Y, dtype=float)
        horizon = max(int(horizon), 1)
        cc = CoupledCompiled.from_models(self.models, u.shape[1])
        thetas = [m.coefficients for m in self.models]
        lag, n, q = cc.max_lag, len(Y), Y.shape[1]
        bounds = [divergence_bounds(Y[:, i]) for i in range(q)]
        out = np.empty((n - lag, q))
        diverged: list[int | None] = [None] * q
        for t in range(lag, n):
            start = max(t - horizon + 1 - lag, 0)  # the window's measured start
            sim, _ = coupled_run(cc, thetas, u[start:t + 1], Y[start:t + 1], bounds)
            out[t - lag] = sim[-1]
            for i in range(q):
                if diverged[i] is None and not np.isfinite(sim[-1, i]):
                    diverged[i] = t
        return out, diverged

    def fits(self, u: np.ndarray, Y: np.ndarray) -> dict:
        """Per output: one-step and coupled free-run fit (%), and where it diverged."""
        Y = np.asarray(Y, dtype=float)
        lag = self.max_lag
        one = self.predict(u, Y)
        free, div = self.simulate(u, Y)
        out = {}
        for i, name in enumerate(self.outputs):
            y = Y[lag:, i]
            out[name] = {"one_step_fit_percent": fit_percent(y, one[:, i]),
                         "free_run_fit_percent": fit_percent(y, free[:, i]),
                         "diverged_at": div[i]}
        return out

    # -- the document ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The document (non-finite numbers as ``null``, as every document)."""
        return json_ready({"schema": MIMO_SCHEMA, "schema_version": MIMO_SCHEMA_VERSION,
                           "outputs": list(self.outputs), "inputs": list(self.inputs),
                           "models": [m.to_dict() for m in self.models],
                           "metadata": self.metadata})

    @classmethod
    def from_dict(cls, doc: dict) -> MimoModel:
        if not isinstance(doc, dict) or doc.get("schema") != MIMO_SCHEMA:
            raise ModelFormatError(f"not a several-output model (schema {MIMO_SCHEMA!r})")
        version = doc.get("schema_version")
        if isinstance(version, bool) or version != MIMO_SCHEMA_VERSION:  # true is not 1
            raise ModelFormatError(f"several-output model version "
                                   f"{doc.get('schema_version')!r} is not supported")
        for key in ("outputs", "inputs", "models"):
            value = doc.get(key)
            if not isinstance(value, list) or (key != "models" and not all(
                    isinstance(v, str) for v in value)):
                raise ModelFormatError(f"{key!r} must be a list" + (
                    " of names" if key != "models" else " of model documents"))
        outputs, inputs = tuple(doc["outputs"]), tuple(doc["inputs"])
        models = []
        for i, d in enumerate(doc["models"]):
            try:
                models.append(NarxModel.from_dict(d))
            except ModelFormatError as exc:
                raise ModelFormatError(f"models[{i}]: {exc}") from None
        if len(models) != len(outputs) or len(outputs) < 2:
            raise ModelFormatError("a several-output model needs one model per output (>= 2)")
        for i, m in enumerate(models):
            others = tuple(o for j, o in enumerate(outputs) if j != i)
            if m.term_space.output != outputs[i] or m.term_space.inputs != inputs + others:
                raise ModelFormatError(f"model {i} does not belong to output {outputs[i]!r}")
        return cls(outputs, inputs, models, dict(check_mimo_metadata(doc.get("metadata") or {})))

    def save(self, path: str | Path) -> Path:
        atomic_write_text(path, document_json(self.to_dict()) + "\n")
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> MimoModel:
        return cls.from_dict(read_json_document(path))


def fit_percent(y: np.ndarray, yhat: np.ndarray) -> float | None:
    """100 (1 - ||y - yhat|| / ||y - mean y||); None when yhat has NaN (diverged)."""
    if not np.all(np.isfinite(yhat)):
        return None
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / np.linalg.norm(y - np.mean(y))))


def in_threads(fn, n: int, at_once: int | None = None) -> list:
    """``[fn(0), ..., fn(n-1)]``, on up to as many threads as there are cores.

    The outputs' identifications are independent (each has its own seed), so the
    results are those of a loop; the compiled kernels release the GIL, so two
    outputs on two cores take little more than one. ``at_once``: at most this
    many at a time (memory).
    """
    workers = min(n, usable_cores(), at_once or n)
    if workers <= 1:
        return [fn(i) for i in range(n)]
    from concurrent.futures import ThreadPoolExecutor

    from ..compiled.registry import jit_available

    jit_available()  # kernels on numba's JIT, which releases the GIL (0.7 s once)

    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, range(n)))


def read_model_document(path: str | Path) -> tuple[NarxModel | MimoModel, dict]:
    """The model in a file, of one output or several, and the document as saved.

    Raises
    ------
    ModelFormatError
        Not a readable model document of either kind (the message says why).
    """
    doc = read_json_document(path)
    try:
        if isinstance(doc, dict) and doc.get("schema") == MIMO_SCHEMA:
            return MimoModel.from_dict(doc), doc
        return NarxModel.from_dict(doc), doc
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFormatError(f"{path}: {exc}") from None

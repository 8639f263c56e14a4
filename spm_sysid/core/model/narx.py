"""A fitted polynomial NARX model: terms, coefficients, prediction, JSON document.

The model is a plain object (no estimator hierarchy): it knows its term space,
which candidate terms it uses and their coefficients, and can predict one step
ahead, simulate free-run and save itself as a versioned JSON document that other
tools (and other languages) can read. See ``docs/model_format.md``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import ModelFormatError
from ..files import atomic_write_text, json_float, json_ready, read_bytes
from ..memory import slice_rows
from .metadata import check_metadata
from .segments import normalise_segments
from .simulation import CompiledModel, divergence_bounds, run_model
from .terms import TermSpace
from .uncertainty import Uncertainty, t_quantile

__all__ = ["MODEL_SCHEMA", "MODEL_SCHEMA_VERSION", "NarxModel"]

MODEL_SCHEMA = "spm_sysid/narx-model"
MODEL_SCHEMA_VERSION = 3
#: Versions this code reads (1: one input named u, no "inputs" in the term space;
#: 2: no coefficient uncertainty).
READABLE_VERSIONS = (1, 2, 3)


#: A linear lag of one signal, ``q(t-3)`` (not a product, power or regressor).
_LINEAR_LAG = re.compile(r"([^()*^ ]+)\(t-\d+\)")


def together_words(group: dict, level: float = 0.95) -> str:
    """One line for :meth:`NarxModel.lags_together`'s group."""
    a, b = group["interval"]
    return (f"the {len(group['terms'])} {group['signal']}(t-i) terms together (each "
            "alone spans zero: they stand in for one another):\n    sum "
            f"{group['sum']:.6g}, std. error {group['standard_error']:.3g}, {level:.0%} "
            f"interval [{a:.6g}, {b:.6g}]")


@dataclass
class NarxModel:
    """Polynomial NARX model ``y(t) = sum_j theta_j * term_j(t)``.

    Attributes
    ----------
    term_space : TermSpace
        The candidate terms the structure was chosen from.
    term_indices : list of int
        Positions of the selected terms in ``term_space.terms`` (ascending).
    coefficients : ndarray, shape (k,)
        One parameter per selected term, same order.
    criterion : str or None
        Name of the criterion that selected the structure.
    criterion_value : float or None
    mse : float or None
        One-step mean squared error on the estimation data.
    n_samples : int or None
        Samples in the estimation data (regression rows = n_samples - max_lag).
    metadata : dict
        Free-form, JSON-serialisable extras (GA settings, seed, validation ...).
    uncertainty : Uncertainty or None
        The coefficients' covariance and how it was obtained
        (:mod:`spm_sysid.core.model.uncertainty`); None when unknown.
    """

    term_space: TermSpace
    term_indices: list[int]
    coefficients: np.ndarray
    criterion: str | None = None
    criterion_value: float | None = None
    mse: float | None = None
    n_samples: int | None = None
    metadata: dict = field(default_factory=dict)
    uncertainty: Uncertainty | None = None

    # -- construction -----------------------------------------------------------------
    def with_coefficients(self, coefficients: np.ndarray) -> NarxModel:
        """The same structure with other coefficients (no uncertainty, no metadata)."""
        return NarxModel(self.term_space, list(self.term_indices),
                         np.asarray(coefficients, dtype=float))

    # -- structure ----------------------------------------------------------------------
    @property
    def mask(self) -> np.ndarray:
        """Chromosome of this structure, shape (n_terms,)."""
        m = np.zeros(self.term_space.n_terms, dtype=bool)
        m[self.term_indices] = True
        return m

    @property
    def terms(self) -> list[str]:
        """Names of the selected terms, in coefficient order."""
        names = self.term_space.term_names()
        return [names[i] for i in self.term_indices]

    def equation(self, decimals: int = 3) -> str:
        """The model as text, like the paper's eq. (1)."""
        parts = []
        for i, (c, name) in enumerate(zip(self.coefficients, self.terms)):
            mag = abs(c)
            num = f"{mag:.{decimals}f}" if mag >= 10 ** -decimals or mag == 0 else f"{mag:.2e}"
            sign = "-" if c < 0 else "+"
            term = "" if name == "1" else name
            if i == 0:
                parts.append(f"{'-' if c < 0 else ''}{num}{term}")
            else:
                parts.append(f" {sign} {num}{term}")
        return f"{self.term_space.output}(t) = " + ("".join(parts) if parts else "0")

    def coefficient_table(self, level: float = 0.95) -> str:
        """The terms with coefficient, standard error and interval, one line each.

        ``*`` marks a term whose interval spans zero (its presence is not supported
        by the data).
        """
        terms = self.terms
        width = max([len(t) for t in terms] + [4])
        head = f"  {'term':<{width}}  {'coefficient':>12}"
        if self.uncertainty is None:
            rows = [head] + [f"  {t:<{width}}  {c:>12.5g}" for t, c in
                             zip(terms, self.coefficients)]
            why = (self.metadata.get("simulation") or {}).get("no_uncertainty")
            return "\n".join(rows + [f"  (no coefficient uncertainty: {why})" if why else
                                      "  (no coefficient uncertainty for this model)"])
        se = self.uncertainty.standard_errors
        iv = self.uncertainty.intervals(self.coefficients, level)
        zero = self.uncertainty.spans_zero(self.coefficients, level)
        rows = [head + f"  {'std. error':>11}  {f'{level:.0%} interval':>25}"]
        for t, c, s_, (a, b), z in zip(terms, self.coefficients, se, iv, zero):
            rows.append(f"  {t:<{width}}  {c:>12.5g}  {s_:>11.3g}  [{a:>11.4g}, {b:>11.4g}]"
                        + ("  *" if z else ""))
        if zero.any():
            rows.append(f"  * interval spans zero ({int(zero.sum())} term(s)); "
                        f"{self.uncertainty.method}, {self.uncertainty.dof} degrees of freedom")
        else:
            rows.append(f"  {self.uncertainty.method}, {self.uncertainty.dof} degrees of "
                        "freedom")
        rows += ["  " + together_words(g, level) for g in self.lags_together(level)]
        return "\n".join(rows)

    def lags_together(self, level: float = 0.95) -> list[dict]:
        """Lags of one signal that each span zero while the data fix their sum.

        The lagged terms of a slowly moving signal stand in for one another: an
        integrating output's ``y(t-1) ... y(t-8)`` may each carry a standard error
        of 8 while their sum, the pole that makes it integrate, is 0.99998 +- 7e-5.
        Each group of a signal's linear lags with two or more terms spanning zero,
        whose sum's standard error (``sqrt(1' Sigma 1)`` over the group) is below a
        tenth of theirs and whose sum's interval leaves out zero: ``signal``,
        ``terms``, ``sum``, ``standard_error``, ``interval``.
        """
        unc = self.uncertainty
        if unc is None:
            return []
        zero = unc.spans_zero(self.coefficients, level)
        se = unc.standard_errors
        groups: dict[str, list[int]] = {}
        for i, term in enumerate(self.terms):
            lag = _LINEAR_LAG.fullmatch(term)
            if lag:
                groups.setdefault(lag.group(1), []).append(i)
        t = t_quantile(max(unc.dof, 1), 0.5 + level / 2.0)
        out = []
        for signal, idx in groups.items():
            alone = [i for i in idx if zero[i]]
            total = float(np.sum(self.coefficients[idx]))
            s = math.sqrt(max(float(unc.covariance[np.ix_(idx, idx)].sum()), 0.0))
            if len(alone) >= 2 and s < 0.1 * float(se[alone].min()) and abs(total) > t * s:
                out.append({"signal": signal, "terms": [self.terms[i] for i in idx],
                            "sum": total, "standard_error": s,
                            "interval": (total - t * s, total + t * s)})
        return out

    # -- prediction -------------------------------------------------------------------
    @cached_property
    def compiled(self) -> CompiledModel:
        """The structure in the simulation kernels' form (built once)."""
        return CompiledModel.from_space(self.term_space, self.term_indices)

    def predict(self, u: np.ndarray, y: np.ndarray,
                segments: list[tuple[int, int]] | None = None,
                horizon: int | None = 1) -> np.ndarray:
        """k-step-ahead prediction for t = max_lag..len-1 (``horizon`` k).

        ``horizon=1`` (default) is one-step prediction from measured u and y;
        k > 1 feeds the model's own outputs back for k steps from the measured
        ones at t - k; None is free-run simulation. With ``segments``, each
        segment's rows, concatenated. A diverging run gives NaN from the
        divergence on (see :meth:`run`).
        """
        if horizon == 1:
            return self._one_step(u, y, segments)
        return self.run(u, y, horizon, segments)[0]

    def _one_step(self, u: np.ndarray, y: np.ndarray,
                  segments: list[tuple[int, int]] | None) -> np.ndarray:
        """One-step predictions; a long record's columns a slice of rows at a time."""
        return np.concatenate([P @ self.coefficients
                               for P, _ in self.regression_slices(u, y, segments)])

    def regression_slices(self, u: np.ndarray, y: np.ndarray,
                          segments: list[tuple[int, int]] | None = None):
        """The structure's regression rows and targets (as :meth:`predict`'s), in slices.

        Pairs ``(P, t)``. A record whose columns fit one slice
        (:func:`~spm_sysid.core.memory.slice_rows`) gives them whole, one pair; a
        longer one a slice of rows at a time, so no array of all its rows by all its
        terms is ever held.
        """
        lag, step = self.term_space.max_lag, slice_rows(len(self.term_indices))
        segs = [(a, b) for a, b in normalise_segments(segments, len(y)) if b - a > lag]
        if sum(b - a - lag for a, b in segs) <= step:
            yield self.term_space.regression(u, y, segments, terms=self.term_indices)
            return
        for a, b in segs:
            for s in range(a + lag, b, step):
                yield self.term_space.regression(u, y, [(s - lag, min(s + step, b))],
                                                 terms=self.term_indices)

    def run(self, u: np.ndarray, y: np.ndarray, horizon: int | None = None,
            segments: list[tuple[int, int]] | None = None) -> tuple[np.ndarray, int | None]:
        """Prediction ``horizon`` steps ahead (None: free-run) and where it diverged.

        Returns the predictions of every segment's rows, concatenated, and the
        first sample index (in ``y``) at which a run left the measured output's
        range (see :mod:`spm_sysid.core.model.simulation`), or None.
        """
        u = self.term_space.inputs_2d(u)
        y = np.asarray(y, dtype=float)
        lag0 = self.term_space.max_lag
        bounds = divergence_bounds(y)
        parts, first = [], None
        for a, b in normalise_segments(segments, len(y)):
            if b - a <= lag0:
                continue
            yhat, at = run_model(self.compiled, self.coefficients, u[a:b], y[a:b], horizon,
                                 bounds)
            parts.append(yhat)
            if at is not None and first is None:
                first = a + at
        return (np.concatenate(parts) if parts else np.empty(0)), first

    def measured(self, y: np.ndarray,
                 segments: list[tuple[int, int]] | None = None) -> np.ndarray:
        """The measured outputs of :meth:`predict`'s rows (every segment's, concatenated)."""
        y = np.asarray(y, dtype=float)
        lag0 = self.term_space.max_lag
        parts = [y[a + lag0:b] for a, b in normalise_segments(segments, len(y)) if b - a > lag0]
        return np.concatenate(parts) if parts else np.empty(0)

    def residuals(self, u: np.ndarray, y: np.ndarray,
                  segments: list[tuple[int, int]] | None = None) -> np.ndarray:
        """One-step residuals y(t) - yhat(t) on the same rows as :meth:`predict`."""
        return self.measured(y, segments) - self.predict(u, y, segments)

    def simulate(self, u: np.ndarray, y_initial: np.ndarray) -> np.ndarray:
        """Free-run simulation: each prediction is fed back as a lagged output.

        Parameters
        ----------
        u : ndarray, shape (n,) or (n, n_inputs)
            Input over the whole horizon.
        y_initial : ndarray, shape (>= max_lag,)
            Measured outputs; the first ``max_lag`` are the initial conditions.
            When it covers the whole horizon, a run that leaves its range by
            far is stopped there (NaN from then on; see :meth:`run`); otherwise
            only a non-finite output stops it.

        Returns
        -------
        ndarray, shape (n - max_lag,)
            Simulated y(t) for t = max_lag..n-1 (same rows as :meth:`predict`).
        """
        ts = self.term_space
        u = ts.inputs_2d(u)
        lag0 = ts.max_lag
        y_initial = np.asarray(y_initial, dtype=float)
        if len(y_initial) < lag0:
            raise ValueError(f"simulation needs {lag0} initial outputs, got {len(y_initial)}")
        if len(y_initial) >= len(u):
            return self.run(u, y_initial[:len(u)])[0]
        y = np.zeros(len(u))
        y[:lag0] = y_initial[:lag0]
        big = np.finfo(float).max
        return run_model(self.compiled, self.coefficients, u, y, None, (-big, big))[0]

    # -- persistence --------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The versioned JSON document (see ``docs/model_format.md``).

        Ready for JSON whatever the metadata holds: a number that is not finite
        is ``null`` (:func:`~spm_sysid.core.files.json_ready`).
        """
        from ... import __version__

        return json_ready({
            "schema": MODEL_SCHEMA,
            "schema_version": MODEL_SCHEMA_VERSION,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "software": {"name": "spm_sysid", "version": __version__},
            "term_space": self.term_space.to_dict(),
            "terms": self.terms,
            "term_indices": list(self.term_indices),
            "coefficients": [float(c) for c in self.coefficients],
            "criterion": None if self.criterion is None else {
                "name": self.criterion,
                "value": json_float(self.criterion_value),
            },
            "mse": json_float(self.mse),
            "n_samples": self.n_samples,
            "uncertainty": None if self.uncertainty is None else self.uncertainty.to_dict(
                self.coefficients),
            "metadata": self.metadata,
        })

    @classmethod
    def from_dict(cls, doc: dict) -> NarxModel:
        """Read a model document, checking schema, version and term consistency."""
        version = _check_header(doc)
        space = _term_space(doc["term_space"], version)
        indices, coefs = _terms(doc, space)
        crit = doc.get("criterion")
        if crit is not None and not (isinstance(crit, dict) and isinstance(crit.get("name"), str)
                                     and (crit.get("value") is None
                                          or _is_number(crit.get("value")))):
            raise ModelFormatError("'criterion' must be null or an object with a 'name' "
                                   "(text) and a 'value' (number or null)")
        crit = crit or {}
        for key in ("mse", "n_samples"):
            value = doc.get(key)
            if value is not None and not (_is_int(value) and value >= 0 if key == "n_samples"
                                          else _is_number(value) and value >= 0):
                raise ModelFormatError(f"{key!r} must be a number >= 0 or null, got "
                                       f"{_show(value)}")
        metadata = check_metadata(doc.get("metadata") or {})
        uncertainty = None
        if version >= 3 and doc.get("uncertainty") is not None:
            try:
                uncertainty = Uncertainty.from_dict(doc["uncertainty"], len(coefs))
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                raise ModelFormatError(f"'uncertainty' is invalid: {exc}") from None
        return cls(term_space=space, term_indices=[int(i) for i in indices],
                   coefficients=np.array(coefs, dtype=float), criterion=crit.get("name"),
                   criterion_value=crit.get("value"), mse=doc.get("mse"),
                   n_samples=doc.get("n_samples"), metadata=metadata, uncertainty=uncertainty)

    def to_json(self) -> str:
        """The document as JSON text."""
        return json.dumps(self.to_dict(), indent=2, allow_nan=False)

    def save(self, path: str | Path) -> Path:
        """Write the JSON document to ``path`` atomically; returns the path."""
        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def load(cls, path: str | Path) -> NarxModel:
        """Read a model saved with :meth:`save` (see :meth:`read_document`)."""
        return cls.read_document(path)[0]

    @classmethod
    def read_document(cls, path: str | Path) -> tuple[NarxModel, dict]:
        """The model in a file and the document as it was saved.

        Only regular files (or pipes) are read, within the memory bound; the
        JSON must be strict (no NaN or Infinity anywhere) and every number in
        range.

        Raises
        ------
        ModelFormatError
            Missing, unreadable or not a model document; the message says why.
        """
        path = Path(path)
        doc = read_json_document(path)
        try:
            return cls.from_dict(doc), doc
        except ModelFormatError as exc:
            raise ModelFormatError(f"{path}: {exc}") from None


def read_json_document(path: str | Path) -> dict:
    """The strict JSON of a model file (no NaN or Infinity), read within the memory bound.

    Raises
    ------
    ModelFormatError
        Missing, unreadable, not text or not valid JSON.
    """
    path = Path(path)
    raw = read_bytes(path, "model file", factor=20, error=ModelFormatError)
    try:
        return json.loads(raw.decode("utf-8-sig"), parse_constant=_reject_constant)
    except UnicodeDecodeError:
        raise ModelFormatError(f"{path} is not a text (JSON) file") from None
    except RecursionError:
        raise ModelFormatError(f"{path} is not a model document (JSON nested too "
                               "deeply)") from None
    except (json.JSONDecodeError, ValueError) as exc:
        raise ModelFormatError(f"{path} is not valid JSON: {exc}") from None


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number (NaN and Infinity are not allowed)")


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
    """A JSON number that fits a float (``10**400`` does not)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        float(x)
    except OverflowError:
        return False
    return True


def _show(x) -> str:
    """A value for a message (a huge integer abbreviated)."""
    text = repr(x)
    return text if len(text) <= 40 else f"{text[:12]}... ({len(text)} digits, beyond any float)"


def _check_header(doc: dict) -> int:
    """The document's schema version, once schema, version and the four parts are there."""
    if not isinstance(doc, dict) or doc.get("schema") != MODEL_SCHEMA:
        raise ModelFormatError(
            f"not a spm_sysid model document (schema must be {MODEL_SCHEMA!r})"
        )
    version = doc.get("schema_version")
    if not _is_int(version) or version not in READABLE_VERSIONS:  # true is not 1
        raise ModelFormatError(
            f"model schema version {version!r} is not supported (this is version "
            f"{MODEL_SCHEMA_VERSION})"
        )
    for key in ("term_space", "terms", "term_indices", "coefficients"):
        if key not in doc:
            raise ModelFormatError(f"model document is incomplete: no {key!r}")
    return version


def _term_space(ts: dict, version: int) -> TermSpace:
    """``term_space`` read back, its fields checked by type first."""
    if not isinstance(ts, dict):
        raise ModelFormatError("'term_space' must be an object")
    for key in ("ny", "nu", "degree", "delay"):
        value = ts.get(key)
        ok = _is_int(value) or (key in ("nu", "delay") and version >= 2
                                and isinstance(value, list) and value
                                and all(_is_int(v) for v in value))
        if not ok:
            raise ModelFormatError(f"term_space.{key} must be an integer, got {value!r}")
    if version >= 2 and not (isinstance(ts.get("inputs", []), list)
                             and all(isinstance(v, str) for v in ts.get("inputs", []))):
        raise ModelFormatError("term_space.inputs must be a list of names")
    if not isinstance(ts.get("constant"), bool):
        raise ModelFormatError(f"term_space.constant must be true or false, got "
                               f"{ts.get('constant')!r}")
    try:
        return TermSpace.from_dict(ts)
    except (TypeError, ValueError) as exc:
        raise ModelFormatError(f"term_space is invalid: {exc}") from None


def _term_lists(doc: dict) -> tuple[list, list, list]:
    """``term_indices``, ``coefficients`` and ``terms``, each a list."""
    indices, coefs, names = doc["term_indices"], doc["coefficients"], doc["terms"]
    for key, value in (("term_indices", indices), ("coefficients", coefs), ("terms", names)):
        if not isinstance(value, list):
            raise ModelFormatError(f"{key!r} must be a list, got {type(value).__name__}")
    return indices, coefs, names


def _terms(doc: dict, space: TermSpace) -> tuple[list, list]:
    """``term_indices`` and ``coefficients``, checked together with ``terms`` and the space."""
    indices, coefs, names = _term_lists(doc)
    bad = [i for i in indices if not _is_int(i)]
    if bad:
        raise ModelFormatError(f"term_indices must be integers, got {bad[0]!r}")
    if len(set(indices)) != len(indices):
        raise ModelFormatError("term_indices lists a term more than once")
    bad = [c for c in coefs if not _is_number(c)]
    if bad:
        raise ModelFormatError(f"coefficients must be numbers, got {_show(bad[0])}")
    if not all(math.isfinite(c) for c in coefs):
        raise ModelFormatError("coefficients must be finite (NaN or inf found)")
    if not all(isinstance(n, str) for n in names):
        raise ModelFormatError("terms must be strings")
    all_names = space.term_names()
    if len(indices) != len(coefs) or len(names) != len(coefs):
        raise ModelFormatError("terms, term_indices and coefficients differ in length")
    if any(i < 0 or i >= len(all_names) for i in indices):
        raise ModelFormatError("a term index lies outside the term space")
    if [all_names[i] for i in indices] != names:
        raise ModelFormatError("term names do not match the term space's order")
    return indices, coefs

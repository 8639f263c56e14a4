"""Identification around an operating point, the model written in the record's own units.

A record whose signals sit far from zero against how much they move (an absolute
joint angle, a temperature in kelvin, a tank's level, a torque that holds a load)
makes its lagged terms nearly proportional to one another and to the constant. An
output that integrates then simulates only while its lag coefficients sum to 1
to many digits, and the selection, which compares structures by their errors,
compares mostly that. The same record moved by a constant gave a different and
much worse model: the tests' simulated joint, its position 30 rad from zero,
simulated another recording at a fit of 7 % instead of 70 % (docs/method.md).

So a job identifies the deviations from the estimation data's means (the
constant a candidate: a model of the record that needs none needs one around its
means), and writes the model in the record's units: each product of deviations
``(x1 - c1)(x2 - c2)...`` expanded into the products of the record's signals it
stands for, the constant among them. That is exact: the document is a polynomial
NARX like any other, read and simulated as any other; its terms are the selected
ones and the lower-degree products and constant their expansion adds
(``metadata.operating_point`` names both). A regressor of differences
(``sign(y(t-1)-y(t-2))``, the friction preset's) does not move with an offset and
is kept as it is; a regressor of the signals themselves (``abs(u(t-1))``) would,
so a space holding one is identified as the record is.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import product

import numpy as np

from ..errors import SettingsError
from .narx import NarxModel
from .terms import TermSpace

__all__ = ["OFFSET_RATIO", "OperatingPoint", "choose_operating_point", "expanded",
           "in_deviations", "in_record_units", "operating_point_words", "own_sign_at",
           "point_clause"]

#: ``auto``: a record is identified around its means when some signal's mean is
#: farther from zero than this many of its standard deviations.
OFFSET_RATIO = 1.0

#: A signal whose mean is within this many of its standard deviations of zero
#: keeps its samples as they are (``auto``): it adds no term, and its offset does
#: not matter.
NEAR_RATIO = 0.1

#: A signal that varies by less than this share of its mean is constant (a
#: setpoint, a held input): it has nothing to centre, and ``auto`` does not count it.
CONSTANT_SHARE = 1e-9

#: A coefficient of the record's units smaller than this share of the sum of
#: its parts' sizes is zero to rounding (the constant of a model that has
#: none, worked out from one that has): it is not written.
ROUNDING_SHARE = 1e-9


@dataclass(frozen=True)
class OperatingPoint:
    """The estimation data's means the deviations are taken from.

    Attributes
    ----------
    inputs : tuple of float
        One per input.
    output : float
    reason : str
        Why the record is identified around it, for the document and the summary.
    """

    inputs: tuple[float, ...]
    output: float
    reason: str

    def centred(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``u`` and ``y`` minus the point (new arrays of the same shapes)."""
        u = np.asarray(u, dtype=float)
        shift = np.asarray(self.inputs) if u.ndim == 2 else self.inputs[0]
        return u - shift, np.asarray(y, dtype=float) - self.output

    def base_offsets(self, space: TermSpace) -> np.ndarray:
        """Each base's offset: the output's for its lags, an input's for its, 0 for regressors."""
        out = np.zeros(space.n_bases)
        for i, (source, _) in enumerate(space.linear):
            out[i] = self.output if source < 0 else self.inputs[source]
        return out

    def to_dict(self, space: TermSpace) -> dict:
        """The document's ``metadata.operating_point`` (the selected terms added by the caller)."""
        return {"output": {space.output: float(self.output)},
                "inputs": {name: float(v) for name, v in zip(space.inputs, self.inputs)},
                "reason": self.reason}


def own_sign_at(point: OperatingPoint | None) -> bool | None:
    """For the ``friction`` preset: whether samples around ``point`` may read the output's sign.

    None (decide from the data) when the output keeps its samples (no point, or
    its output not moved); False when the output is taken around its mean: the
    sign of a deviation is not the record's.
    """
    return None if point is None or point.output == 0.0 else False


def choose_operating_point(setting: str, u_rows: np.ndarray, y_rows: np.ndarray,
                           space: TermSpace) -> tuple[OperatingPoint | None, str | None]:
    """The point a record is identified around (None: as it is), and why not when it would be.

    Parameters
    ----------
    setting : str
        ``auto`` (around the means when some signal's mean is farther from zero
        than :data:`OFFSET_RATIO` of its standard deviations), ``mean`` (always
        around the means) or ``none``.
    u_rows, y_rows : ndarray
        The estimation samples (inputs one column each).
    space : TermSpace
        The candidate terms, with their regressors: a regressor that moves with an
        offset keeps the record as it is, and the second value says so.

    Raises
    ------
    SettingsError
        ``mean`` asked for with a regressor that moves with an offset.
    """
    if setting == "none":
        return None, None
    u = np.asarray(u_rows, dtype=float).reshape(len(y_rows), -1)
    y = np.asarray(y_rows, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):  # magnitudes are the problem's to refuse
        means = np.append(u.mean(axis=0), y.mean())
        spread = np.append(u.std(axis=0), y.std())
    if not (np.all(np.isfinite(means)) and np.all(np.isfinite(spread))):
        return None, None
    varies = spread > CONSTANT_SHARE * np.abs(means)
    names = (*space.inputs, space.output)
    far = [f"{n}'s mean {m:.6g} is {abs(m) / s:.3g} standard deviations from zero"
           for n, m, s, v in zip(names, means, spread, varies)
           if v and abs(m) > OFFSET_RATIO * s]
    moved = varies & (np.abs(means) > (NEAR_RATIO * spread if setting == "auto" else 0.0))
    if setting == "auto" and not far or not np.any(moved):
        return None, None
    means = np.where(moved, means, 0.0)
    reason = "; ".join(far) if far else "asked for (operating_point: mean)"
    point = OperatingPoint(tuple(float(v) for v in means[:-1]), float(means[-1]), reason)
    moving = _moving_regressors(space, u, y, point)
    if not moving:
        return point, None
    why = (f"the regressor(s) {', '.join(moving)} change when their signals move by a "
           "constant, so the record was identified as it is")
    if setting == "mean":
        raise SettingsError(f"operating_point: mean: {why}; give operating_point none")
    return None, f"{reason}, but {why}"


def _moving_regressors(space: TermSpace, u: np.ndarray, y: np.ndarray,
                       point: OperatingPoint) -> list[str]:
    """The space's regressors that differ between the record and its deviations."""
    if not space.regressors:
        return []
    rows = min(len(y), 2000)
    du, dy = point.centred(u[:rows], y[:rows])
    return [text for text, a, b in zip(space.regressors,
                                       space.regressor_columns(u[:rows], y[:rows]),
                                       space.regressor_columns(du, dy))
            if not np.allclose(a, b, rtol=1e-9, equal_nan=True,
                               atol=1e-12 * max(float(np.nanmax(np.abs(a), initial=0.0)), 1.0))]


def in_record_units(model: NarxModel, point: OperatingPoint) -> NarxModel:
    """The model of deviations from ``point`` as the same model of the record's signals.

    Each selected term's product of deviations is expanded, and the constant gains
    the point's output (the model's output is a deviation too); the coefficients
    and their covariance map through the same linear map, so the free run, the
    predictions and the output bands are those of the model identified. The term
    space gains the constant. The model's metadata (the same dict) records the point.
    """
    whole = expanded(model, point)
    doc = point.to_dict(model.term_space)
    doc["selected_terms"] = model.terms
    doc["terms_added"] = len(set(whole.terms) - set(model.terms))
    model.metadata["operating_point"] = doc
    return whole


def in_deviations(model: NarxModel, point: OperatingPoint) -> NarxModel:
    """A model of the record's signals as the same model of their deviations from ``point``.

    The inverse of :func:`in_record_units` (the record's signals are their
    deviations plus the point); the metadata is a copy, left as it was.
    """
    back = OperatingPoint(tuple(-v for v in point.inputs), -point.output, point.reason)
    return replace(expanded(model, back), metadata=dict(model.metadata))


def expanded(model: NarxModel, point: OperatingPoint) -> NarxModel:
    """The model with every signal ``x`` read as ``x - c`` and ``point.output`` added.

    The products expanded into the term space with the constant; coefficients
    zero to rounding (:data:`ROUNDING_SHARE`) left out; the covariance mapped.
    The metadata is the model's own dict.
    """
    space = model.term_space
    whole = replace(space, constant=True)
    index = {term: i for i, term in enumerate(whole.terms)}
    offsets = point.base_offsets(space)
    expansion = np.zeros((whole.n_terms, len(model.term_indices)))
    for j, i in enumerate(model.term_indices):
        term = space.terms[i]
        for kept in product((True, False), repeat=len(term)):
            factor = np.prod([-offsets[b] for b, keep in zip(term, kept) if not keep])
            expansion[index[tuple(b for b, keep in zip(term, kept) if keep)], j] += factor
    shift = np.zeros(whole.n_terms)  # the output is its deviation plus the point's output
    shift[index[()]] = point.output
    theta = expansion @ model.coefficients + shift
    parts = np.abs(expansion) @ np.abs(model.coefficients) + np.abs(shift)
    rows = np.flatnonzero(np.abs(theta) > ROUNDING_SHARE * parts)
    expansion, theta = expansion[rows], theta[rows]
    uncertainty = model.uncertainty
    if uncertainty is not None:
        cov = expansion @ uncertainty.covariance @ expansion.T
        uncertainty = replace(uncertainty, covariance=(cov + cov.T) / 2.0)
    return replace(model, term_space=whole, term_indices=[int(r) for r in rows],
                   coefficients=theta, uncertainty=uncertainty)


def operating_point_words(doc: dict | None) -> str:
    """The document's ``metadata.operating_point`` in a clause ('' when it has none)."""
    if not doc:
        return ""
    if "output" not in doc:
        return f"identified as recorded: {doc['reason']}"
    added = doc.get("terms_added", 0)
    return (f"identified around the estimation data's means ({point_clause(doc)}), "
            f"written in the record's units: {len(doc.get('selected_terms', []))} selected "
            f"terms" + (f" and the {added} their expansion adds" if added else ""))


def point_clause(doc: dict) -> str:
    """``q = 30.003; <reason>``: the signals moved (a signal kept as it is has 0), and why."""
    values = ", ".join(f"{name} = {value:.6g}"
                       for name, value in {**doc["output"], **doc["inputs"]}.items() if value)
    return f"{values}; {doc['reason']}"

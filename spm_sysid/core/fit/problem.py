"""The regression problem of an identification, built once.

Every step from a record to a model -- the GA search, its certification, the
simulation-focused selection, the lag proposal, a study's runs, the final fit
-- works on the same least-squares problem: the candidate terms' columns over
the regression rows of the record's segments, and the target. :class:`Problem`
builds it once:

1. the segments are explicit (``[start, stop)`` ranges; the whole record is one
   segment), and only those longer than the largest lag are kept;
2. the signals are scaled by powers of two (exact: data of any magnitude fit
   alike; coefficients and criteria are given back in the user's units);
3. the candidate matrix is built (rows never cross from one segment to the
   next; :meth:`TermSpace.regression`);
4. candidate columns that can never be part of an identifiable structure are
   set aside and named: zero on every row (every term of an input that is
   zero), or proportional to an earlier candidate's column (every lag of a
   constant input but the first; an input equal to the output).

It then serves what the steps need: a structure evaluator over the usable
columns (:meth:`evaluator`; the Gram matrix and triangular factor it holds are
computed once and shared by every criterion), the mapping between the usable
columns and the whole term space (:meth:`expand`, :meth:`restrict`), and the
least-squares fit of one structure (:meth:`fit`, :meth:`model`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..defaults import FACTOR_SLICE_BYTES, STRUCTURE_SLICE_BYTES
from ..errors import DataError, TooFewSamplesError
from ..memory import check_memory
from ..model.segments import normalise_segments, rows_segments, usable_segments
from ..model.terms import TermSpace, power_of_two_scale
from .criteria import Criterion, get_criterion
from .lstsq import DEFAULT_RANK_TOL, column_norms, structure_fit

if TYPE_CHECKING:
    from ..model.narx import NarxModel

__all__ = ["LARGE_SPACE", "Problem", "StructureFit", "check_magnitudes", "check_samples",
           "excluded_columns", "fit_structure", "validate_signals"]

#: In larger term spaces the data need rows for structures of this many terms only.
LARGE_SPACE = 100

#: Largest and smallest RMS of the output that squared sums (SSE, MSE) still hold.
Y_RMS_RANGE = (1e-150, 1e150)

#: Columns equal after normalisation to this many bits are the same column.
_BITS = 36


# -- checks at the boundary ------------------------------------------------------------


def check_samples(n_samples: int, max_lag: int, n_terms: int = 1) -> None:
    """Raise DataError when there are too few samples to fit with these lags.

    A fit needs more regression rows (``n_samples - max_lag``) than the largest
    possible structure has terms.
    """
    rows = n_samples - max_lag
    if rows <= n_terms:
        raise TooFewSamplesError(
            f"too few samples: {n_samples} samples give {max(rows, 0)} regression rows "
            f"with maximum lag {max_lag}, but {n_terms + 1} or more are needed for "
            f"{n_terms} candidate terms (need at least {max_lag + n_terms + 1} samples)"
        )


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    return peak * float(np.sqrt(np.mean(np.square(x / peak)))) if peak > 0 else 0.0


def check_magnitudes(u: np.ndarray, y: np.ndarray, term_space: TermSpace) -> None:
    """Refuse signals whose magnitudes double precision cannot carry through a fit.

    Fits run on data scaled by powers of two (exact), but the SSE, the MSE and
    the coefficients are reported in the user's units: the output's RMS must lie
    in :data:`Y_RMS_RANGE` (else its squared sums under- or overflow), and every
    coefficient's unit factor (output scale over input and output scales to the
    term's powers) must be a normal float.

    Raises
    ------
    DataError
        Naming the signal, its RMS and what to do.
    """
    ry = _rms(y)
    low, high = Y_RMS_RANGE
    if ry > 0 and not low <= ry <= high:
        raise DataError(
            f"the output {term_space.output} has RMS {ry:.1e}: beyond {low:.0e}..{high:.0e}, "
            "its squared errors cannot be represented in double precision; rescale it "
            f"(e.g. multiply by 1e{-int(np.floor(np.log10(ry)))}) and scale the model's "
            "output back")
    u2 = term_space.inputs_2d(u)
    su = np.array([power_of_two_scale(c) for c in u2.T])
    factors = term_space.coefficient_factors(su, power_of_two_scale(y),
                                             term_space.regressor_scales(u2, y))
    bad = ~(np.isfinite(factors) & (factors >= np.finfo(float).tiny))
    if bad.any():
        term = term_space.term_names()[int(np.flatnonzero(bad)[0])]
        sizes = ", ".join(f"{n} {_rms(c):.1e}" for n, c in zip(term_space.inputs, u2.T))
        raise DataError(
            f"the signals' magnitudes (RMS: {sizes}; {term_space.output} {ry:.1e}) are too far "
            f"apart for the coefficients of terms such as {term} to be represented in double "
            "precision; rescale the inputs and the output to similar magnitudes")


def validate_signals(u, y, term_space: TermSpace,
                     segments: list[tuple[int, int]] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert u, y at the public boundary.

    Raises
    ------
    DataError
        Not 1-D, different lengths, non-finite values, too few samples, or
        magnitudes double precision cannot carry (:func:`check_magnitudes`).
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    m = term_space.n_inputs
    if y.ndim != 1 or not (u.ndim == 1 and m == 1 or u.ndim == 2 and u.shape[1] == m):
        raise DataError(f"y must be 1-D and u of shape (n,) or (n, {m}) for {m} input(s) "
                        f"{', '.join(term_space.inputs)}; got shapes {u.shape} and {y.shape}")
    if len(u) != len(y):
        raise DataError(f"u and y must have the same length, got {len(u)} and {len(y)}")
    for name, arr in (("u", u), ("y", y)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise DataError(
                f"{name} has {bad.size} non-finite value(s) (NaN or inf), first at index "
                f"{bad[0]}"
            )
    # Rows for the largest structure of the space -- or, in spaces of more than
    # LARGE_SPACE terms, for structures of LARGE_SPACE terms: larger ones simply cannot
    # be fitted on this data (rank-deficient, never selected).
    need = min(term_space.n_terms, LARGE_SPACE)
    if segments is None:
        check_samples(len(y), term_space.max_lag, need)
    else:
        rows = sum(b - a - term_space.max_lag for a, b in segments)
        if rows <= need:
            raise TooFewSamplesError(
                f"too few samples: {len(segments)} segment(s) longer than the largest lag "
                f"({term_space.max_lag}) give {max(rows, 0)} regression rows, but "
                f"{need + 1} or more are needed for {term_space.n_terms} candidate terms")
    check_magnitudes(u, y, term_space)
    return u, y


def working_bytes(rows: int, terms: int) -> int:
    """The memory a problem of ``rows`` x ``terms`` candidate terms works in, at most.

    The candidate matrix (built and reduced in slices: no copy of it), the slices
    the evaluator works on (a scaled one, its stack on the factor and QR's copy),
    the five a structure's fit holds (its columns, unit-norm, QR's copy and Q), and
    the evaluator's Gram matrix and triangular factor of all candidate terms.
    """
    matrix = 8 * rows * (terms + 1)
    slices = 3 * min(matrix, FACTOR_SLICE_BYTES) + 5 * min(matrix, STRUCTURE_SLICE_BYTES)
    return matrix + slices + 2 * 8 * (terms + 2) ** 2


def excluded_columns(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns to leave out of the search: those no structure needs.

    Parameters
    ----------
    P : ndarray, shape (N, M)
        The candidate columns, one per term.

    Returns
    -------
    zero : ndarray of bool, shape (M,)
        Columns that are zero on every row.
    duplicate_of : ndarray of int, shape (M,)
        For a non-zero column proportional to an earlier non-zero column (equal
        after scaling to unit norm and fixing the sign, to about 1e-11), the index
        of the first such column; -1 otherwise.

    Notes
    -----
    Only a column proportional to another is left out: any structure holding it
    has the fit of the same structure holding the other instead. A column that
    is another one *plus a number* (a two-level input's square, ``u^2 = (a + b) u
    - a b``) stays: alone it is a term of its own, which the other term can match
    only with the constant beside it, one term more (the dryer at 84 candidates:
    leaving such squares out cost its AIC optimum 1.73). Columns are compared by
    hashing their normalised values rounded to ``_BITS`` bits, O(N M); a pair
    that rounding splits stays in, and the evaluator's rank test still scores
    structures holding both as rank-deficient (as it scores ``u``, ``u^2`` and
    the constant together).
    """
    P = np.asarray(P, dtype=float)
    norms = column_norms(P)
    zero = norms == 0
    duplicate_of = np.full(P.shape[1], -1)
    _mark_repeats(np.flatnonzero(~zero), lambda j: _key(P[:, j], norms[j]), duplicate_of)
    return zero, duplicate_of


def _key(col: np.ndarray, norm: float) -> bytes:
    """A column scaled to unit norm, its sign fixed, rounded to ``_BITS`` bits: as bytes."""
    col = col / norm
    pivot = col[int(np.argmax(np.abs(col)))]
    return np.round(np.ldexp(col * np.sign(pivot), _BITS)).astype(np.int64).tobytes()


def _mark_repeats(columns: np.ndarray, key: Callable[[int], bytes], duplicate_of: np.ndarray
                  ) -> None:
    """Each column whose key an earlier column of ``columns`` has: marked with that column."""
    # keyed by a digest of the rounded column (a whole key per column would be another
    # copy of the matrix); a digest match is confirmed on the keys themselves
    first: dict[bytes, int] = {}
    for j in columns:
        k = key(j)
        digest = hashlib.blake2b(k, digest_size=16).digest()
        if digest in first and key(first[digest]) == k:
            duplicate_of[j] = first[digest]
        else:
            first.setdefault(digest, j)


# -- the problem ----------------------------------------------------------------------------


@dataclass(frozen=True)
class StructureFit:
    """The least-squares fit of one structure, in the user's units.

    Attributes
    ----------
    mask : ndarray of bool, shape (n_terms,)
        The structure over the whole term space.
    coefficients : ndarray, shape (k,)
        One per selected term, in term order.
    sse : float
        Sum of squared one-step residuals.
    residuals : ndarray, shape (rows,)
        One-step residuals of the problem's rows.
    r_factor : ndarray, shape (k, k)
        Upper-triangular factor R of the selected columns scaled to unit norm
        (``A / norms = Q R``); with ``column_norms`` it gives the coefficients'
        covariance, ``sigma^2 (R^T R)^-1`` on the unit-norm columns.
    column_norms : ndarray, shape (k,)
        Norms of the selected columns in the user's units.
    """

    mask: np.ndarray
    coefficients: np.ndarray
    sse: float
    residuals: np.ndarray
    r_factor: np.ndarray
    column_norms: np.ndarray


class Problem:
    """The least-squares problem of one record and one term space (see the module doc).

    Build it with :meth:`from_signals` (checked at the boundary).

    Attributes
    ----------
    term_space : TermSpace
    u : ndarray, shape (n, n_inputs)
    y : ndarray, shape (n,)
        The signals as given (simulations and refinements run on them).
    segments : list of (start, stop)
        The segments that give regression rows (always explicit).
    u_scale : ndarray, shape (n_inputs,)
    y_scale : float
        The powers of two the signals were divided by.
    columns : ndarray, shape (rows, stored)
        Every candidate term's column of the scaled signals but the products of
        regressors (no candidates: on a long record with the friction preset
        they were half the matrix); :meth:`column_index` maps terms to them.
    target : ndarray, shape (rows,)
        The scaled output of the regression rows.
    zero : ndarray of bool, shape (n_terms,)
    duplicate_of : ndarray of int, shape (n_terms,)
        See :func:`excluded_columns`.
    usable : ndarray of bool, shape (n_terms,)
        Columns the search may use (neither zero nor a repeat, nor a product of
        regressors: :attr:`~spm_sysid.core.model.terms.TermSpace.regressor_products`).
    row_times : ndarray of int, shape (rows,)
        The sample index t of each regression row.
    fed_back : tuple of str
        The inputs that are other outputs of a coupled model (the data check does
        not ask about their lag 0); set by the job, empty by default.
    """

    fed_back: tuple[str, ...] = ()

    def __init__(self, term_space: TermSpace, u: np.ndarray, y: np.ndarray,
                 segments: Sequence[tuple[int, int]]) -> None:
        self.term_space = term_space
        self.u = term_space.inputs_2d(u)
        self.y = np.asarray(y, dtype=float)
        self.segments = normalise_segments(segments, len(self.y))  # checked here, once
        self.u_scale = np.array([power_of_two_scale(c) for c in self.u.T])
        self.y_scale = power_of_two_scale(self.y)
        self.r_scale = term_space.regressor_scales(self.u, self.y)
        scales = (self.u_scale, self.y_scale, self.r_scale) if term_space.regressors else None
        products = term_space.regressor_products
        stored = np.flatnonzero(~products)
        self._position = np.full(term_space.n_terms, -1)
        self._position[stored] = np.arange(len(stored))
        self.columns, self.target = term_space.regression(
            self.u / self.u_scale, self.y / self.y_scale, self.segments,
            terms=stored if products.any() else None, scales=scales)
        lag = term_space.max_lag
        self.row_times = np.concatenate([np.arange(a + lag, b) for a, b in self.segments])
        zero, duplicate_of = excluded_columns(self.columns)
        self.zero = np.zeros(term_space.n_terms, dtype=bool)
        self.zero[stored] = zero
        self.duplicate_of = np.full(term_space.n_terms, -1)
        self.duplicate_of[stored] = np.where(duplicate_of >= 0, stored[duplicate_of], -1)
        self.usable = ~self.zero & (self.duplicate_of < 0) & ~products
        self._factors = term_space.coefficient_factors(self.u_scale, self.y_scale, self.r_scale)
        self._evaluators: dict[float, object] = {}  # the shared numbers, by rank_tol
        self._norms: np.ndarray | None = None

    @classmethod
    def from_signals(cls, u, y, term_space: TermSpace | None = None,
                     segments: Sequence[tuple[int, int]] | None = None) -> Problem:
        """Check the signals (at the public boundary) and build the problem.

        ``segments`` (``[start, stop)`` ranges; None: the whole record) are checked
        and those no longer than the largest lag dropped.

        Raises
        ------
        DataError
            Bad shapes, non-finite values, too few samples, out-of-range
            magnitudes, no usable segment, an output that is constant (or zero)
            throughout.
        MemoryLimitError
            The candidate matrix and the evaluator's factors would exceed the
            memory bound.
        """
        term_space = term_space or TermSpace()
        n = len(np.asarray(y))
        given = segments is not None
        segs = normalise_segments(segments, n)
        segs, _, _ = usable_segments(segs, term_space.max_lag)
        if not segs:
            raise DataError(f"no segment of the data is longer than the largest lag "
                            f"({term_space.max_lag}): nothing to fit")
        u, y = validate_signals(u, y, term_space, segs if given else None)
        name = term_space.output
        if not np.any(y):
            raise DataError(f"the output {name} is zero throughout: there is nothing to "
                            "identify")
        if np.all(y == y[0]):  # a stuck sensor: y(t) = y(t-1) would "fit" it exactly
            raise DataError(f"the output {name} is constant ({y[0]:g} throughout; a stuck or "
                            "disconnected sensor?): there is nothing to identify")
        rows = sum(b - a - term_space.max_lag for a, b in segs)
        m = term_space.n_terms - int(term_space.regressor_products.sum())
        # on top of what the process holds when the user set the bound
        check_memory(working_bytes(rows, m),
                     f"the regression matrix of {rows} rows x {m} candidate terms", held=True)
        return cls(term_space, u, y, segs)

    # -- sizes and names ------------------------------------------------------------------
    @property
    def rows(self) -> int:
        """Regression rows (the N of the criteria)."""
        return len(self.target)

    @property
    def n_samples(self) -> int:
        """Samples in the segments (rows plus each segment's initial conditions)."""
        return sum(b - a for a, b in self.segments)

    @property
    def sse_scale(self) -> float:
        """SSE in the user's units per SSE of the scaled target."""
        return self.y_scale * self.y_scale

    @property
    def whole(self) -> bool:
        """True when the problem's rows are those of the whole record, in one segment."""
        return self.segments == [(0, len(self.y))]

    @property
    def column_norms(self) -> np.ndarray:
        """Every candidate column's norm in the user's units, shape (n_terms,).

        0 for a product of regressors (not a candidate; its column is not built).
        """
        if self._norms is None:
            norms = np.zeros(self.term_space.n_terms)
            stored = self._position >= 0
            with np.errstate(divide="ignore", invalid="ignore"):
                norms[stored] = (column_norms(self.columns) * self.y_scale
                                 / self._factors[stored])
            self._norms = norms
        return self._norms

    def column_index(self, terms) -> np.ndarray:
        """The positions in :attr:`columns` of these term indices.

        Raises
        ------
        ValueError
            A term is a product of regressors (no candidate: its column is not built).
        """
        at = self._position[np.asarray(terms, dtype=int)]
        if (at < 0).any():
            raise ValueError("a structure holds a product of two regressors, which is no "
                             "candidate term (write such a product as one expression)")
        return at

    def excluded_terms(self) -> dict[str, dict]:
        """The terms set aside, by reason.

        ``{"zero": [...], "duplicate": {term: first}, "regressor_products": count}``.
        """
        names = self.term_space.term_names()
        return {"zero": [names[i] for i in np.flatnonzero(self.zero)],
                "duplicate": {names[i]: names[self.duplicate_of[i]]
                              for i in np.flatnonzero(self.duplicate_of >= 0)},
                "regressor_products": int(self.term_space.regressor_products.sum())}

    # -- the search's view: the usable columns --------------------------------------------
    def evaluator(self, criterion: str | Criterion = "aic", rank_tol: float = DEFAULT_RANK_TOL,
                  max_terms: int = 0):
        """A new :class:`StructureEvaluator` over the usable columns (masks of that length).

        Its Gram matrix and triangular factor are computed once per problem and
        shared by every evaluator; each evaluator has its own cache, so every
        search on the problem starts afresh (a study's runs in one process are
        independent of one another). ``max_terms`` > 0: larger structures score +inf.
        """
        from .evaluator import StructureEvaluator

        crit = get_criterion(criterion)
        base = self._evaluators.get(rank_tol)
        if base is None:
            base = StructureEvaluator(self.columns, self.target, crit, rank_tol=rank_tol,
                                      sse_scale=self.sse_scale,
                                      columns=self.column_index(np.flatnonzero(self.usable)))
            self._evaluators[rank_tol] = base
        return base.with_criterion(crit, max_terms)

    def constant_split(self) -> tuple[int | None, np.ndarray]:
        """The constant's column and the columns that are another plus a number.

        Over the evaluator's columns: the constant's index (None: not a usable
        candidate) and, for each column equal to an earlier non-constant column
        times a number plus a number (a two-level input's square), that column's
        index (-1 otherwise). Such a column stands for the other in a structure
        with the constant and is a term of its own without it: the certification
        searches the two cases apart (:mod:`~spm_sysid.core.search.split`).
        """
        columns = np.flatnonzero(self.usable)
        source = np.full(len(columns), -1)
        if not (self.term_space.constant and len(columns) and columns[0] == 0):
            return None, source
        P = self.columns
        columns = self.column_index(columns)
        centred = np.array([np.linalg.norm(P[:, j] - P[:, j].mean()) for j in columns[1:]])
        moving = np.flatnonzero(centred > 1e-9 * column_norms(P)[columns[1:]]) + 1
        _mark_repeats(moving, lambda i: _key(P[:, columns[i]] - P[:, columns[i]].mean(),
                                             centred[i - 1]), source)
        return 0, source

    def expand(self, masks: np.ndarray) -> np.ndarray:
        """Masks over the usable columns -> masks over the whole term space."""
        masks = np.asarray(masks, dtype=bool)
        full = np.zeros(masks.shape[:-1] + (self.term_space.n_terms,), dtype=bool)
        full[..., self.usable] = masks
        return full

    def restrict(self, masks: np.ndarray) -> np.ndarray:
        """Masks over the whole term space -> masks over the usable columns.

        Raises
        ------
        ValueError
            A mask selects a column that was set aside.
        """
        masks = np.asarray(masks, dtype=bool)
        if (masks[..., ~self.usable]).any():
            raise ValueError("a structure selects a term that was set aside (zero or a repeat "
                             "of another on this data)")
        return masks[..., self.usable]

    # -- one structure ------------------------------------------------------------------
    def fit(self, mask: np.ndarray, rank_tol: float = DEFAULT_RANK_TOL,
            rows: np.ndarray | None = None) -> StructureFit:
        """Least-squares fit (Householder QR) of the structure ``mask`` (whole term space).

        ``rows`` (bool over the problem's rows) fits on those rows only (a fold of
        validated selection); the residuals are then those rows'.

        Raises
        ------
        ValueError
            An empty structure, or regressors linearly dependent on this data.
        """
        mask = np.asarray(mask, dtype=bool)
        ts = self.term_space
        if mask.shape != (ts.n_terms,):
            raise ValueError(f"mask must have {ts.n_terms} entries, got {mask.shape}")
        if not mask.any():
            raise ValueError("cannot fit a structure with no terms")
        # the structure's columns, read a slice of rows at a time on a long record
        res, residuals = structure_fit(self.columns, self.target,
                                       self.column_index(np.flatnonzero(mask)), rows, rank_tol)
        if res.rank_deficient:
            names = [ts.term_names()[i] for i in np.flatnonzero(mask)]
            raise ValueError(f"the regressors {names} are linearly dependent on this data")
        factors = self._factors[mask]
        coefficients = res.coefficients * factors
        residuals = residuals * self.y_scale
        return StructureFit(mask=mask.copy(), coefficients=coefficients,
                            sse=res.sse * self.sse_scale, residuals=residuals,
                            r_factor=res.r_factor,
                            column_norms=res.column_norms * self.y_scale / factors)

    def model(self, mask: np.ndarray, fit: StructureFit | None = None, **info):
        """The least-squares :class:`NarxModel` of the structure ``mask``.

        ``fit`` is the structure's :meth:`fit` when the caller has it; ``info``
        are further model fields (``criterion``, ``criterion_value``, ``metadata``).
        """
        from ..model.narx import NarxModel
        from ..model.uncertainty import from_least_squares

        fit = self.fit(mask) if fit is None else fit
        rows = len(fit.residuals)  # all the problem's rows, or a fold's
        return NarxModel(term_space=self.term_space,
                         term_indices=[int(i) for i in np.flatnonzero(fit.mask)],
                         coefficients=fit.coefficients, mse=fit.sse / rows,
                         n_samples=self.n_samples,
                         uncertainty=from_least_squares(fit.r_factor, fit.column_norms,
                                                        fit.sse, rows), **info)


def fit_structure(u: np.ndarray, y: np.ndarray, mask: np.ndarray, term_space: TermSpace,
                  segments: list[tuple[int, int]] | None = None, **info) -> NarxModel:
    """Least-squares fit (Householder QR) of the structure ``mask`` on u, y.

    A convenience for one structure: it builds the regression problem
    (:class:`Problem`) and fits it; code that fits several structures on the
    same data builds the problem once and calls its :meth:`Problem.model`.
    ``segments`` (``[start, stop)`` ranges of contiguous samples) keep every
    regression row inside one segment; None is the whole record. ``info``
    goes to the model (``criterion``, ``criterion_value`` ...).

    Raises
    ------
    ValueError
        If the structure is empty or its regressors are linearly dependent.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (term_space.n_terms,):
        raise ValueError(f"mask must have {term_space.n_terms} entries, got {mask.shape}")
    if not mask.any():
        raise ValueError("cannot fit a structure with no terms")
    problem = Problem(term_space, u, y, rows_segments(segments, len(y), term_space.max_lag))
    return problem.model(mask, **info)

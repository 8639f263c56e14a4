"""Candidate terms of a polynomial NARX model and the regression matrix.

The term order is fixed and documented because a GA chromosome is one bit per
term in exactly this order:

1. the constant term ``1`` (only when ``constant=True``);
2. the linear terms: ``y(t-1) .. y(t-ny)`` then ``u(t-d) .. u(t-d-nu+1)``;
3. the products of degree 2, 3, ... ``degree``: for each degree, every
   multiset of linear terms in lexicographic order of their positions in
   step 2 (``itertools.combinations_with_replacement``), e.g. ``y(t-1)^2``,
   ``y(t-1)*y(t-2)``, ..., ``u(t-4)^2``.

With the paper's setting (ny=4, nu=4, degree=2, delay=1, no constant) this gives
8 linear and 36 quadratic terms: 44 in all.

Regressors (:mod:`.regressors`: ``sign(y(t-1)-y(t-2))``, ...) are building
blocks after the lagged signals: the *bases* are the lagged signals, then the
regressors, and a term is a multiset of at most ``degree`` bases. Without
regressors the bases are the lagged signals and the order above is unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from itertools import combinations_with_replacement

import numpy as np

from ..settings import check
from .regressors import Expr, RegressorError, canonical, evaluate, parse

__all__ = ["MAX_TERMS", "TermSpace", "power_of_two_scale"]

#: Largest term space (the memory bound usually refuses earlier, with the size needed).
MAX_TERMS = 100_000
#: Bytes of candidate-matrix rows built at a time (the products' working columns).
ROW_BLOCK_BYTES = 16 << 20


def power_of_two_scale(x: np.ndarray) -> float:
    """The power of two nearest the RMS of ``x`` (1 for an all-zero signal).

    Dividing by a power of two is exact in floating point, so scaled data give
    the same fits as the original bit for bit, while data of any magnitude
    (1e-100 or 1e100) stay clear of overflow and underflow in the products.
    """
    x = np.asarray(x, dtype=float)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    if not peak > 0 or not np.isfinite(peak):
        return 1.0
    rms = peak * float(np.sqrt(np.mean(np.square(x / peak))))
    return float(np.ldexp(1.0, int(np.round(np.log2(rms)))))


@dataclass(frozen=True)
class TermSpace:
    """The space of candidate NARX terms: one output and one or several inputs.

    Parameters
    ----------
    ny : int
        Maximum output lag; output lags are 1..ny.
    nu : int or tuple of int
        Number of lags of each input (one value for all inputs, or one per input);
        input i's lags are ``delay_i .. delay_i + nu_i - 1``.
    degree : int
        Highest polynomial degree (the paper's "nonlinearity"): products across
        the output and all inputs up to this degree.
    delay : int or tuple of int
        Each input's smallest lag. 0 lets u(t) act on y(t) (direct feed-through);
        the output's lags start at 1, so the model stays causal.
    constant : bool
        Whether a constant term is a candidate.
    inputs : tuple of str
        Input names for term names (``torque(t-2)``); default ``u`` for one input,
        ``u1, u2, ...`` for several. Their number fixes the number of inputs when
        ``nu`` and ``delay`` are single values.
    output : str
        The output's name in term names (default ``y``).
    regressors : tuple of str
        Expressions of lagged signals (:mod:`.regressors`), stored in their
        canonical text; presets are expanded before (:func:`.presets.expand_presets`).
    """

    ny: int = 4
    nu: int | tuple[int, ...] = 4
    degree: int = 2
    delay: int | tuple[int, ...] = 1
    constant: bool = False
    inputs: tuple[str, ...] = ()
    output: str = "y"
    regressors: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        # ranges and types are declared once, in the settings schema
        for name in ("ny", "degree", "constant"):
            object.__setattr__(self, name, check(name, getattr(self, name)))
        nus = self.nu if isinstance(self.nu, (tuple, list)) else (self.nu,)
        delays = self.delay if isinstance(self.delay, (tuple, list)) else (self.delay,)
        names = tuple(self.inputs) if isinstance(self.inputs, (tuple, list)) else (self.inputs,)
        m = max(len(nus), len(delays), len(names), 1)
        for label, values in (("nu", nus), ("delay", delays), ("inputs", names)):
            if len(values) not in (0, 1, m) or (label != "inputs" and not values):
                raise ValueError(f"{label} gives {len(values)} values for {m} inputs (give "
                                 f"one value for all inputs, or one per input)")
        if names and len(names) != m:
            which = " and ".join(label for label, values in (("nu", nus), ("delay", delays))
                                 if len(values) == m)
            raise ValueError(f"{which} give{'' if ' and ' in which else 's'} {m} values, but there "
                             f"{'is 1 input' if len(names) == 1 else f'are {len(names)} inputs'}"
                             f" ({', '.join(map(str, names))}): give one value per input, or "
                             "one for all")
        nus = tuple(check("nu", v) for v in (nus * m if len(nus) == 1 else nus))
        delays = tuple(check("delay", v) for v in (delays * m if len(delays) == 1 else delays))
        if not names:
            names = ("u",) if m == 1 else tuple(f"u{i + 1}" for i in range(m))
        if len(set(names + (self.output,))) != m + 1 or not all(
                isinstance(n, str) and n.isidentifier() for n in names + (self.output,)):
            raise ValueError(f"signal names must be distinct identifiers, got inputs {names} "
                             f"and output {self.output!r}")
        # one value per input is stored as a plain int (the single-input form)
        object.__setattr__(self, "nu", nus[0] if m == 1 else nus)
        object.__setattr__(self, "delay", delays[0] if m == 1 else delays)
        object.__setattr__(self, "inputs", names)
        object.__setattr__(self, "regressors", self._canonical_regressors())
        if self.ny + sum(nus) == 0:
            raise ValueError("at least one of ny, nu must be positive")
        if self.n_terms > MAX_TERMS:
            raise ValueError(
                f"this term space has {self.n_terms} candidate terms; at most {MAX_TERMS} "
                "are supported (lower the lags or the degree)")

    def _canonical_regressors(self) -> tuple[str, ...]:
        """The regressors in canonical text, each once; a RegressorError names a bad one."""
        given = self.regressors
        if isinstance(given, str):
            given = (given,)
        texts = []
        for text in given:
            e = parse(text, self.output, tuple(self.inputs))
            if not e.signals():
                raise RegressorError(f"regressor {text!r} reads no signal (a constant is the "
                                     "constant term)")
            texts.append(canonical(e))
        if len(set(texts)) != len(texts):
            raise RegressorError(f"a regressor is listed twice: {', '.join(texts)}")
        return tuple(texts)

    @cached_property
    def regressor_exprs(self) -> tuple[Expr, ...]:
        """The regressors as expressions."""
        return tuple(parse(t, self.output, tuple(self.inputs)) for t in self.regressors)

    @property
    def n_bases(self) -> int:
        """Building blocks of the terms: the lagged signals, then the regressors."""
        return len(self.linear) + len(self.regressors)

    def is_output_lag(self, index: int) -> bool:
        """Base ``index`` is a lagged output ``y(t-l)`` (not a regressor, not an input)."""
        return index < len(self.linear) and self.linear[index][0] < 0

    def reads_input(self, index: int) -> bool:
        """Base ``index`` reads an input (a lagged input, or a regressor of one)."""
        if index < len(self.linear):
            return self.linear[index][0] >= 0
        e = self.regressor_exprs[index - len(self.linear)]
        return any(name != self.output for name, _ in e.signals())

    # -- the linear building blocks -------------------------------------------------
    @property
    def n_inputs(self) -> int:
        return len(self.inputs)

    @property
    def nus(self) -> tuple[int, ...]:
        """Lags per input."""
        return self.nu if isinstance(self.nu, tuple) else (self.nu,)

    @property
    def delays(self) -> tuple[int, ...]:
        """Delay per input."""
        return self.delay if isinstance(self.delay, tuple) else (self.delay,)

    @cached_property
    def linear(self) -> list[tuple[int, int]]:
        """The lagged signals as ``(source, lag)`` pairs, in term order.

        ``source`` is -1 for the output and 0, 1, ... for the inputs.
        """
        out = [(-1, lag) for lag in range(1, self.ny + 1)]
        for i, (nu, d) in enumerate(zip(self.nus, self.delays)):
            out += [(i, lag) for lag in range(d, d + nu)]
        return out

    def signal_name(self, source: int) -> str:
        """The output's or input ``source``'s name."""
        return self.output if source < 0 else self.inputs[source]

    @property
    def order(self) -> int:
        """The most lags any signal has (the output's ny, each input's nu): the ARX order."""
        return max([self.ny] + list(self.nus))

    @property
    def max_lag(self) -> int:
        """Largest lag; the first regression row is at t = max_lag."""
        return max([self.ny] + [d + nu - 1 for nu, d in zip(self.nus, self.delays) if nu]
                   + [lag for e in self.regressor_exprs for _, lag in e.signals()])

    @cached_property
    def terms(self) -> list[tuple[int, ...]]:
        """Every candidate term as a sorted tuple of indices into :attr:`linear`.

        The constant term is the empty tuple.
        """
        n_bases = self.n_bases
        out: list[tuple[int, ...]] = [()] if self.constant else []
        for deg in range(1, self.degree + 1):
            out.extend(combinations_with_replacement(range(n_bases), deg))
        return out

    @cached_property
    def term_degrees(self) -> np.ndarray:
        """Each term's degree, a regressor factor counting twice (a regressor is nonlinear).

        What the selection reads as linear (degree 1) or not; without regressors
        the number of factors.
        """
        n_lin = len(self.linear)
        return np.array([len(t) + sum(1 for i in t if i >= n_lin) for t in self.terms],
                        dtype=np.int64)

    @cached_property
    def regressor_products(self) -> np.ndarray:
        """Terms with two or more regressor factors (bool per term): no search offers them.

        A product of regressors is one function of the signals, which a user who
        wants it writes as one expression (``sign(y(t-1)-y(t-2))*abs(u(t-1))``);
        the friction preset's are functions of one step that repeat the others or
        nearly (``sign(x)*abs(x) = x``, ``sign(x)^2 = 1`` off zero steps,
        ``abs(x)^2 = x^2``) and only invite overfits. The term space keeps them,
        so documents keep their term numbers.
        """
        n_lin = len(self.linear)
        return np.array([sum(1 for i in t if i >= n_lin) >= 2 for t in self.terms], dtype=bool)

    @property
    def n_terms(self) -> int:
        """Number of candidate terms (chromosome length)."""
        from math import comb

        n_lin = self.ny + sum(self.nus) + len(self.regressors)
        return int(self.constant) + sum(
            comb(n_lin + deg - 1, deg) for deg in range(1, self.degree + 1)
        )

    def term_names(self) -> list[str]:
        """Readable names such as ``y(t-1)*u(t-2)``, ``u(t-1)^2``, ``y(t-1)*torque(t)``."""
        return list(self._names)

    @cached_property
    def _names(self) -> tuple[str, ...]:
        names = []
        for term in self.terms:
            if not term:
                names.append("1")
                continue
            parts = []
            for idx in sorted(set(term)):
                power = term.count(idx)
                parts.append(self.base_name(idx) + (f"^{power}" if power > 1 else ""))
            names.append("*".join(parts))
        return names

    def base_name(self, index: int) -> str:
        """``y(t-1)``, ``torque(t)`` or a regressor's text."""
        lin = self.linear
        if index >= len(lin):
            return self.regressors[index - len(lin)]
        src, lag = lin[index]
        return f"{self.signal_name(src)}({'t' if lag == 0 else f't-{lag}'})"

    def term_factors(self, index: int) -> list[tuple[str, int, int]]:
        """Term ``index`` as its factors ``(signal name, lag, power)``; [] for ``1``.

        For readers that evaluate the model without parsing names (the typed ROS
        message ``NarxTerm``).
        """
        term = self.terms[index]
        lin = self.linear
        return [(self.signal_name(lin[i][0]), lin[i][1], term.count(i)) if i < len(lin)
                else (self.regressors[i - len(lin)], 0, term.count(i))
                for i in sorted(set(term))]

    def to_dict(self) -> dict:
        """Plain-data form for JSON documents (model schema version 2)."""
        one = self.n_inputs == 1
        out = {"ny": int(self.ny), "nu": int(self.nu) if one else list(self.nu),
               "degree": int(self.degree),
               "delay": int(self.delay) if one else list(self.delay),
               "constant": bool(self.constant), "inputs": list(self.inputs),
               "output": self.output}
        if self.regressors:
            out["regressors"] = list(self.regressors)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> TermSpace:
        """Inverse of :meth:`to_dict`; version-1 documents (one input ``u``) load too.

        Missing keys take the defaults (a configuration may give only some).
        """
        def seq(v):
            return tuple(v) if isinstance(v, list) else v

        d = cls.__dataclass_fields__
        return cls(ny=data.get("ny", d["ny"].default), nu=seq(data.get("nu", d["nu"].default)),
                   degree=data.get("degree", d["degree"].default),
                   delay=seq(data.get("delay", d["delay"].default)),
                   constant=data.get("constant", d["constant"].default),
                   inputs=tuple(data.get("inputs") or ()), output=data.get("output", "y"),
                   regressors=tuple(data.get("regressors") or ()))

    def coefficient_factors(self, u_scale, y_scale: float, r_scale=None) -> np.ndarray:
        """Per-term factors from scaled-data coefficients to the user's units, (n_terms,).

        The coefficients were fitted on ``u / u_scale`` (one scale per input) and
        ``y / y_scale``, regressor columns divided by ``r_scale`` (one per
        regressor; default 1). A term with ``a`` output factors, ``b_i`` factors
        of input i and ``c_r`` of regressor r has ``theta = theta_scaled *
        y_scale**(1 - a) * prod_i u_scale_i**(-b_i) * prod_r r_scale_r**(-c_r)``;
        with powers of two the factors are exact (``ldexp``, no overflow on the way).
        """
        ey = np.frexp(y_scale)[1] - 1
        eu = [np.frexp(s)[1] - 1 for s in np.atleast_1d(np.asarray(u_scale, dtype=float))]
        lin = self.linear
        n_lin = len(lin)
        er = [np.frexp(s)[1] - 1 for s in np.atleast_1d(
            np.ones(len(self.regressors)) if r_scale is None else np.asarray(r_scale, float))]
        exps = np.array([ey * (1 - sum(1 for i in term if i < n_lin and lin[i][0] < 0))
                         - sum(eu[lin[i][0]] for i in term if i < n_lin and lin[i][0] >= 0)
                         - sum(er[i - n_lin] for i in term if i >= n_lin)
                         for term in self.terms], dtype=np.int64)
        with np.errstate(over="ignore", under="ignore"):  # inf or 0: refused by identify
            return np.ldexp(np.ones(self.n_terms), exps)

    # -- the regression matrix -------------------------------------------------------
    def inputs_2d(self, u: np.ndarray) -> np.ndarray:
        """``u`` as shape (n, n_inputs) (a 1-D array is the single input)."""
        u = np.asarray(u, dtype=float)
        u = u[:, None] if u.ndim == 1 else u
        if u.ndim != 2 or u.shape[1] != self.n_inputs:
            raise ValueError(f"this term space has {self.n_inputs} input(s); u has shape "
                             f"{np.shape(u)}")
        return u

    def lagged(self, u: np.ndarray, y: np.ndarray, scales=None) -> np.ndarray:
        """Matrix of the bases, shape ``(N, n_bases)``, rows t = max_lag..len-1.

        The lagged signals, then the regressors. ``scales``: ``(u_scale, y_scale,
        r_scale)`` when u and y are scaled data: regressors are evaluated on the
        signals in the user's units (scaled back, exactly) and divided by their
        own scale.
        """
        u = self.inputs_2d(u)
        y = np.asarray(y, dtype=float)
        start, stop = self.max_lag, len(y)
        cols = []
        for src, lag in self.linear:
            sig = y if src < 0 else u[:, src]
            cols.append(sig[start - lag : stop - lag])
        cols += self.regressor_columns(u, y, scales)
        if not cols:
            return np.empty((stop - start, 0))
        return np.column_stack(cols)

    def regressor_columns(self, u: np.ndarray, y: np.ndarray, scales=None) -> list[np.ndarray]:
        """Each regressor's values at t = max_lag..len-1 (see :meth:`lagged` for ``scales``)."""
        if not self.regressors:
            return []
        u = self.inputs_2d(u)
        y = np.asarray(y, dtype=float)
        r_scale = np.ones(len(self.regressors))
        if scales is not None:
            u = u * np.asarray(scales[0], dtype=float)
            y = y * float(scales[1])
            r_scale = np.asarray(scales[2], dtype=float)
        start, stop = self.max_lag, len(y)
        index = {name: i for i, name in enumerate(self.inputs)}

        def get(name: str, lag: int) -> np.ndarray:
            sig = y if name == self.output else u[:, index[name]]
            return sig[start - lag: stop - lag]

        return [np.broadcast_to(evaluate(e, get), (max(stop - start, 0),)) / r
                for e, r in zip(self.regressor_exprs, r_scale)]

    def regressor_scales(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The power of two nearest each regressor's RMS on u, y (the user's units)."""
        return np.array([power_of_two_scale(c[np.isfinite(c)])
                         for c in self.regressor_columns(u, y)])

    def regression_matrix(self, u: np.ndarray, y: np.ndarray,
                          terms: Sequence[int] | None = None, scales=None,
                          out: np.ndarray | None = None) -> np.ndarray:
        """Candidate regressors, shape ``(N, n_terms)`` with ``N = len(y) - max_lag``.

        Column ``j`` is term ``j`` of :attr:`terms` evaluated at t = max_lag..len-1.
        Products are built degree by degree from the previous degree's columns, so
        each column costs one vectorised multiplication. With ``terms`` (indices),
        only those columns, in that order (a model's own regressors). Built into
        ``out`` when given (rows by columns), :data:`ROW_BLOCK_BYTES` of rows at a
        time: a long record's matrix is the only large array made.
        """
        lin = self.lagged(u, y, scales)
        width = self.n_terms if terms is None else len(terms)
        if out is None:
            out = np.empty((lin.shape[0], width))
        step = max(1, ROW_BLOCK_BYTES // (8 * max(width + lin.shape[1], 1)))
        for a in range(0, lin.shape[0], step):
            self._fill(lin[a:a + step], terms, out[a:a + step])
        return out

    def _fill(self, lin: np.ndarray, terms: Sequence[int] | None, out: np.ndarray) -> None:
        """Rows of the candidate matrix from the same rows of the lagged signals."""
        if terms is not None:
            out[:] = 1.0
            for c, j in enumerate(terms):
                for i in self.terms[j]:
                    out[:, c] *= lin[:, i]
            return
        columns: dict[tuple[int, ...], np.ndarray] = {(): np.ones(len(lin))}
        for i in range(lin.shape[1]):
            columns[(i,)] = lin[:, i]
        for term in self.terms:
            if len(term) > 1 and term not in columns:
                columns[term] = columns[term[:-1]] * lin[:, term[-1]]
        for c, term in enumerate(self.terms):
            out[:, c] = columns[term]

    def target(self, y: np.ndarray) -> np.ndarray:
        """The regression target y(t) for t = max_lag..len-1."""
        return np.asarray(y, dtype=float)[self.max_lag :]

    def regression(self, u: np.ndarray, y: np.ndarray,
                   segments: list[tuple[int, int]] | None = None,
                   terms: Sequence[int] | None = None,
                   scales=None) -> tuple[np.ndarray, np.ndarray]:
        """Regression matrix and target built inside each segment, stacked.

        ``segments`` are ``[start, stop)`` index ranges of contiguous samples
        (see :mod:`spm_sysid.core.model.segments`); rows never cross from one segment to
        the next. Segments with no more than ``max_lag`` samples give no row.
        None means the whole record is one segment. ``terms``: only these
        columns (see :meth:`regression_matrix`).
        """
        if segments is None:
            return self.regression_matrix(u, y, terms, scales), self.target(y)
        width = self.n_terms if terms is None else len(terms)
        kept = [(a, b) for a, b in segments if b - a > self.max_lag]
        out = np.empty((sum(b - a - self.max_lag for a, b in kept), width))
        row = 0
        for a, b in kept:  # each segment's rows built in place: no stacked copies
            rows = b - a - self.max_lag
            self.regression_matrix(u[a:b], y[a:b], terms, scales, out=out[row:row + rows])
            row += rows
        target = np.concatenate([self.target(y[a:b]) for a, b in kept]) if kept else np.empty(0)
        return out, target

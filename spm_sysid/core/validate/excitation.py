"""Can these data identify this space? A check before any search.

For a :class:`~spm_sysid.core.fit.problem.Problem` it reports:

* **persistent excitation** of each input: the largest order n for which n
  lagged copies of the input are linearly independent on the data (smallest
  over largest eigenvalue of their Gram matrix above :data:`PE_TOL`). An input
  persistently exciting of order p can tell apart at most p of its own lags: a
  constant input has order 1, a sine order 2, white noise every order tried;
* the **candidate matrix**: its size against the rows (``rows per candidate``),
  its condition number (columns scaled to unit norm), and the candidate terms
  it cannot identify -- zero on every row, repeating an earlier column, or
  nearly a combination of others (a pivoted QR of the problem's triangular
  factor: a squared relative pivot below the evaluator's rank tolerance; spaces
  of at most :data:`COLLINEAR_LIMIT` usable terms);
* a **refusal** when nothing can be identified (no candidate term varies), and
  **warnings** otherwise: too few rows per candidate, an input too simple for
  its lags, terms that cannot be identified, an ill-conditioned matrix, a
  constant output, an output held at its largest or smallest value
  (:mod:`.clipping`), a record sampled far faster than its signals move
  (:func:`oversampling`: then ``--decimate`` may fit better), an output whose
  signs explain what a polynomial does not (:mod:`.friction`: then
  ``--regressors friction`` may).

``spm-sysid check-data`` prints the report; ``identify`` prints its warnings
first; the node's answer, ``/diagnostics`` and the model document carry them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..compiled.kernels import pivoted_qr
from ..defaults import (
    COLLINEAR_LIMIT,
    CONDITION_WARN,
    GLITCH_FACTOR,
    OVERSAMPLED_POWER,
    OVERSAMPLING_FACTORS,
    PE_TOL,
    ROWS_PER_TERM,
)
from ..errors import DataError
from .clipping import clipped_ends, describe_clipping
from .feedthrough import describe_feedthrough, within_sample
from .friction import FRICTION_LEVEL, strongest_friction_sign
from .held_output import describe_held_output, held_output
from .spikes import describe_spikes, output_spikes

__all__ = ["COLLINEAR_LIMIT", "DataCheck", "check_problem", "describe_check",
           "describe_glitches", "describe_wraps", "excitation_order", "glitches",
           "oversampling", "wraps"]

#: The turns an angle may be wrapped at, and their names: radians and degrees.
TURNS = ((2.0 * np.pi, "2*pi"), (360.0, "360"))

#: Terms named on one line of the report (the document lists them all).
SHOWN_TERMS = 20



def glitches(y: np.ndarray, segments=None, limit: int = 5) -> list[int]:
    """The samples of ``y`` far outside the rest (at most ``limit``, the worst first).

    A sample counts when its distance from the median is more than
    :data:`GLITCH_FACTOR` times the 99th percentile of all distances: one spike
    of 1e4 in a signal of unit size, never a step, a saturation or a sine.
    Signals that do not vary on 99 % of their samples have no glitches.
    """
    y = np.asarray(y, dtype=float)
    if segments:
        index = np.concatenate([np.arange(a, b) for a, b in segments])
    else:
        index = np.arange(len(y))
    x = y[index]
    if len(x) < 100 or not np.all(np.isfinite(x)):
        return []
    d = np.abs(x - np.median(x))
    ref = float(np.quantile(d, 0.99))
    if not ref > 0:
        return []
    far = np.flatnonzero(d > GLITCH_FACTOR * ref)
    if len(far) > max(1, len(x) // 1000):  # many: part of the signal, not a glitch
        return []
    return [int(index[i]) for i in far[np.argsort(-d[far])][:limit]]


def describe_glitches(y: np.ndarray, at: list[int], name: str = "y") -> str:
    """The glitches of :func:`glitches` in words ('' when none)."""
    if not at:
        return ""
    d = np.abs(np.asarray(y, dtype=float) - np.median(y))
    ref = float(np.quantile(d, 0.99))
    shown = ", ".join(f"sample {i}: {y[i]:.6g}" for i in at[:3])
    return (f"the output {name} has {len(at)} sample(s) far outside the rest ({shown}; "
            f"{d[at[0]] / ref:.0f} times the 99th percentile of its distance from the "
            "median): a glitch (a spike, a bad read)? It dominates any least-squares fit: "
            "remove it, or split the record there")


def wraps(x: np.ndarray, segments=None) -> tuple[float, str, list[int]] | None:
    """Where ``x`` wraps around like an angle: (turn, its name, the samples after each jump).

    An angle kept within one turn (``[-pi, pi)``, ``[0, 360)``) jumps by nearly a
    turn each time it passes the end: a continuous joint, a wheel, a yaw. Those
    jumps are not the plant's, and a model of them is none of the plant's. A
    signal counts when it stays within one turn, 99 % of its steps are below a
    twentieth of a turn (a signal that moves that fast is not told from its
    wraps), and every step of more than half a turn is a turn less a step of
    that size: a turn minus the jump within three times the 99th percentile of
    the other steps (a step input from 0 to 6 is not a wrap at 2*pi, the input
    does not move between its samples). None otherwise.
    """
    x = np.asarray(x, dtype=float)
    bounds = segments or [(0, len(x))]
    steps = [(a + 1, np.diff(x[a:b])) for a, b in bounds if b - a > 1]
    if not steps or not np.all(np.isfinite(x)):
        return None
    span = float(np.max(x) - np.min(x))
    for turn, name in TURNS:
        if span > 1.001 * turn:
            continue
        at = [start + int(i) for start, d in steps
              for i in np.flatnonzero(np.abs(d) > turn / 2)]
        if not at:
            continue
        jumps = np.abs(np.concatenate([d for _, d in steps]))
        big = jumps > turn / 2
        if np.all(big):
            continue
        typical = float(np.quantile(jumps[~big], 0.99))
        if typical < turn / 20 and np.all(np.abs(turn - jumps[big])
                                           <= 3.0 * typical + 1e-9 * turn):
            return turn, name, at
    return None


def describe_wraps(x: np.ndarray, segments, name: str, role: str) -> str:
    """The wraps of :func:`wraps` in words ('' when none)."""
    found = wraps(x, segments)
    if found is None:
        return ""
    _, turn, at = found
    return (f"the {role} {name} jumps by nearly a turn ({turn}) at {len(at)} sample(s) (the "
            f"first at sample {at[0]}) and stays within one turn: a wrapped angle? Its model "
            "would fit the jumps, not the plant: unwrap it before identifying "
            "(numpy.unwrap; a continuous joint's position in /joint_states wraps)")


def excitation_order(u: np.ndarray, segments, max_order: int) -> int:
    """Order of persistent excitation of one input (up to ``max_order``).

    The largest n for which the n lagged copies of the input, ``u(t-1) ..
    u(t-n)`` over the rows every segment has for n lags, are linearly
    independent to within :data:`PE_TOL` (smallest over largest eigenvalue of
    their Gram matrix). 0 for a zero input.
    """
    max_order = max(int(max_order), 1)
    gram = np.zeros((max_order, max_order))
    for a, b in segments:
        x = np.asarray(u[a:b], dtype=float)
        if len(x) <= max_order:
            continue
        lagged = np.column_stack([x[max_order - j:len(x) - j] for j in range(1, max_order + 1)])
        gram += lagged.T @ lagged
    if not np.trace(gram) > 0:
        return 0
    order = 0
    for n in range(1, max_order + 1):
        w = np.linalg.eigvalsh(gram[:n, :n])
        if w[-1] <= 0 or w[0] / w[-1] <= PE_TOL:
            break
        order = n
    return order


def oversampling(u: np.ndarray, y: np.ndarray, segments) -> int:
    """How many times faster than its signals move a record is sampled (0: not notably).

    The largest K of :data:`OVERSAMPLING_FACTORS` for which every input and the
    output hold :data:`OVERSAMPLED_POWER` of their power below 1/(2K) of the
    sampling rate (:func:`_power_spectra`, on at most the first 2^18 samples of
    the longest segment). A joint sampled at 1 kHz that moves at a few hertz is
    such a record: its output's second difference is mostly measurement noise,
    which biases least squares on lagged outputs (docs/cli.md, ``--decimate``).
    """
    a, b = max(segments, key=lambda s: s[1] - s[0]) if segments else (0, len(y))
    b = min(b, a + 2 ** 18)
    signals = np.column_stack([np.asarray(u, dtype=float).reshape(len(y), -1)[a:b],
                               np.asarray(y, dtype=float)[a:b]])
    if b - a < 64 or np.any(np.ptp(signals, axis=0) == 0):
        return 0
    freq, power = _power_spectra(signals, min(4096, (b - a) // 4))
    total = power.sum(axis=0)
    found = 0
    for k in OVERSAMPLING_FACTORS:
        if np.all(power[freq <= 0.5 / k].sum(axis=0) >= OVERSAMPLED_POWER * total):
            found = k
    return found


def _power_spectra(x: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """Each column's power by frequency (cycles per sample), Welch's way.

    The average of Hann-windowed periodograms of half-overlapping pieces, the
    mean removed; numpy's FFT, so the data check imports no scipy (``identify`` starts fast).
    """
    x = x - x.mean(axis=0)
    window = np.hanning(length)[:, None]
    starts = range(0, len(x) - length + 1, length // 2)
    power = sum(np.abs(np.fft.rfft(window * x[s:s + length], axis=0)) ** 2 for s in starts)
    return np.fft.rfftfreq(length), power


@dataclass
class DataCheck:
    """The report of :func:`check_problem` (see the module doc)."""

    rows: int
    candidates: int
    usable: int
    excitation: dict[str, int]
    lags: dict[str, int]
    tried_order: int
    condition: float | None
    zero_terms: list[str] = field(default_factory=list)
    repeated_terms: dict[str, str] = field(default_factory=dict)
    collinear_terms: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    refusal: str | None = None

    @property
    def rows_per_candidate(self) -> float:
        return self.rows / max(self.usable, 1)

    def lines(self) -> list[str]:
        """The report for people (``spm-sysid check-data``)."""
        out = [f"rows: {self.rows}; candidate terms: {self.candidates} ({self.usable} usable); "
               f"{self.rows_per_candidate:.1f} rows per usable candidate"]
        for name, order in self.excitation.items():
            shown = f">= {order}" if order >= self.tried_order else str(order)
            out.append(f"input {name}: persistently exciting of order {shown} "
                       f"({self.lags[name]} lag(s) in the space)")
        if self.condition is not None:
            out.append(f"condition number of the candidate matrix (unit-norm columns): "
                       f"{self.condition:.3g}")
        if self.zero_terms:
            out.append(f"zero on every row: {', '.join(self.zero_terms)}")
        if self.repeated_terms:
            out.append("repeating an earlier term: " + ", ".join(
                f"{a} (= {b})" for a, b in self.repeated_terms.items()))
        if self.collinear_terms:
            shown = self.collinear_terms[:SHOWN_TERMS]
            more = len(self.collinear_terms) - len(shown)
            out.append(f"nearly a combination of others ({len(self.collinear_terms)}): "
                       f"{', '.join(shown)}" + (f", ... ({more} more; all in the model "
                                               "document's metadata.data_check)" if more
                                               else ""))
        out += [f"warning: {w}" for w in self.warnings]
        if self.refusal:
            out.append(f"refused: {self.refusal}")
        return out

    def to_dict(self) -> dict:
        """Plain data for the model document (``metadata.data_check``)."""
        return {"rows": self.rows, "candidates": self.candidates, "usable": self.usable,
                "rows_per_candidate": round(self.rows_per_candidate, 3),
                "excitation_order": dict(self.excitation), "lags": dict(self.lags),
                "condition": self.condition, "collinear_terms": list(self.collinear_terms),
                "warnings": list(self.warnings)}


def describe_check(doc: dict | None) -> str:
    """One line of a model document's ``metadata.data_check`` ('' when none)."""
    if not doc:
        return ""
    text = (f"data check: {doc['rows']} rows, {doc['usable']} of {doc['candidates']} candidate "
            f"terms usable ({doc['rows_per_candidate']:.1f} rows per term)")
    for name, order in doc.get("excitation_order", {}).items():
        text += (f"; input {name} persistently exciting of order {order}"
                 f" ({doc['lags'][name]} lags)")
    if doc.get("condition") is not None:
        text += f"; condition number {doc['condition']:.2g}"
    return text


def check_problem(problem, rank_tol: float = 1e-9, criterion: str | None = None) -> DataCheck:
    """Check what the problem's data can identify (see the module doc).

    ``criterion``: the name of the criterion the search will use (its warnings say
    what suits it).

    Raises
    ------
    DataError
        When nothing can be identified (the refusal's reason).
    """
    ts = problem.term_space
    names = ts.term_names()
    excluded = problem.excluded_terms()
    usable = int(problem.usable.sum())
    tried = max(ts.nus) + 2
    excitation = {name: excitation_order(problem.u[:, i], problem.segments, tried)
                  for i, name in enumerate(ts.inputs)}
    lags = dict(zip(ts.inputs, ts.nus))
    check = DataCheck(rows=problem.rows, candidates=ts.n_terms, usable=usable,
                      excitation=excitation, lags=lags, tried_order=tried, condition=None,
                      zero_terms=excluded["zero"], repeated_terms=excluded["duplicate"])
    if usable == 0:
        check.refusal = ("no candidate term varies on this data (every one is zero or "
                         "repeats another): there is nothing to identify")
        raise DataError(check.refusal)
    if usable <= COLLINEAR_LIMIT:
        ev = problem.evaluator()
        diag, piv = np.empty(usable), np.empty(usable, dtype=np.int64)
        pivoted_qr(np.ascontiguousarray(ev.factor[:, :usable].T), diag, piv)
        diag = diag[:min(usable, ev.factor.shape[0])]
        if diag.size and diag[0] > 0:
            check.condition = float(diag[0] / max(diag[-1], np.finfo(float).tiny))
        usable_names = [names[i] for i in np.flatnonzero(problem.usable)]
        weak = [usable_names[piv[j]] for j in range(len(diag)) if diag[j] ** 2 < rank_tol]
        check.collinear_terms = sorted(weak, key=usable_names.index)
    _warn(check, problem, criterion)
    return check


def _warn(check: DataCheck, problem, criterion: str | None = None) -> None:
    ts = problem.term_space
    w = check.warnings
    w += _signal_warnings(problem)
    if check.rows_per_candidate < ROWS_PER_TERM:
        strong = criterion in ("bic", "aicc")
        w.append(f"{check.rows} rows for {check.usable} candidate terms (fewer than "
                 f"{ROWS_PER_TERM} per candidate): "
                 + (f"even {criterion.upper()} may select too many terms; prefer max_terms, "
                    "fewer lags or selection: validated" if strong else
                    f"a criterion with a weak penalty ({(criterion or 'AIC').upper()}) may "
                    "select far too many terms; prefer BIC or AICc, max_terms, or fewer lags"))
    for name, order in check.excitation.items():
        need = check.lags[name]
        if order == 0 and need:
            w.append(f"input {name} is zero: its terms cannot be identified")
        elif order < need:
            kind = "constant" if order == 1 else f"persistently exciting of order {order} only"
            w.append(f"input {name} is {kind}: of its {need} lags only {order} can be told "
                     "apart, the terms of the others cannot be identified")
    if check.repeated_terms:
        terms = list(check.repeated_terms)
        w.append(f"{len(terms)} term(s) repeat others on this data and were left out "
                 f"({', '.join(terms[:6])}{', ...' if len(terms) > 6 else ''})")
    if check.collinear_terms:
        terms = check.collinear_terms
        w.append(f"{len(terms)} term(s) are nearly combinations of others and cannot be "
                 f"identified together with them ({', '.join(terms[:6])}"
                 f"{', ...' if len(terms) > 6 else ''})")
    if check.condition is not None and check.condition > CONDITION_WARN:
        w.append(f"the candidate matrix is ill-conditioned (condition number "
                 f"{check.condition:.2g}): coefficients of correlated terms are poorly "
                 "determined (see their intervals)")
    y = problem.y
    if np.ptp(y) == 0:
        w.append(f"the output {ts.output} is constant")
    factor = oversampling(problem.u, problem.y, problem.segments)
    if factor:
        w.append(f"every input and the output hold {OVERSAMPLED_POWER:.0%} of their power "
                 f"below 1/{2 * factor} of the sampling rate: the record is sampled about "
                 f"{factor}x faster than they move, so the step from one sample to the next "
                 "may be small against measurement noise, which biases the fit of lagged "
                 f"outputs (gains, friction); a slower rate may fit better: --decimate "
                 f"{factor // 4} (docs/cli.md)")
    if not ts.regressors:
        hint = _friction_hint(problem, max(factor // 4, 1))
        if hint:
            w.append(hint)
    hint = _feedthrough_hint(problem)
    if hint:
        w.append(hint)


def _signal_warnings(problem) -> list[str]:
    """What the samples themselves show, in the order the warnings are given.

    Bad samples first (they explain the warnings after them), then an output held
    at an end or in regular runs, then a wrapped angle.
    """
    ts = problem.term_space
    found = [_bad_samples(problem),
             describe_clipping(clipped_ends(problem.y, problem.segments), ts.output),
             describe_held_output(held_output(problem.y, problem.segments), ts.output)]
    for signal, name, role in [(problem.y, ts.output, "output"),
                               *((problem.u[:, i], n, "input") for i, n in
                                 enumerate(ts.inputs))]:
        found.append(describe_wraps(signal, problem.segments, name, role))
    return [text for text in found if text]


def _bad_samples(problem) -> str:
    """A glitch far outside the output's range, else spikes within it ('' when neither).

    Spikes are not looked for beside a glitch: its least squares reads them wrong.
    """
    ts = problem.term_space
    glitch = describe_glitches(problem.y, glitches(problem.y, problem.segments), ts.output)
    return glitch or describe_spikes(output_spikes(problem.y, problem.u, problem.segments),
                                     ts.output)


def _feedthrough_hint(problem) -> str:
    """The within-sample test's warning on the longest segment ('' when no input acts so)."""
    ts = problem.term_space
    a, b = max(problem.segments, key=lambda s: s[1] - s[0]) if problem.segments \
        else (0, len(problem.y))
    used = [i for i, nu in enumerate(ts.nus) if nu and ts.inputs[i] not in problem.fed_back]
    found = within_sample(problem.y[a:b], problem.u[a:b][:, used],
                          [ts.delays[i] for i in used], [ts.inputs[i] for i in used])
    return describe_feedthrough(found, ts.output)


def _friction_hint(problem, advised_every: int) -> str:
    """The friction test's warning on the longest segment ('' when it shows none)."""
    ts = problem.term_space
    a, b = max(problem.segments, key=lambda s: s[1] - s[0]) if problem.segments \
        else (0, len(problem.y))
    found = strongest_friction_sign(problem.y[a:b], problem.u[a:b], max(ts.ny, 2),
                                    max(ts.nus, default=1), advised_every)
    if found is None or not found.shows_friction:
        return ""
    signs = " and ".join(s.replace("y(", f"{ts.output}(") for s in found.signs)
    rate = "the record's rate" if found.every == 1 else f"every {found.every}th sample"
    return (f"{signs} explain {found.share:.0%} of the squared residual of a linear ARX "
            f"model with cubic terms (p < {FRICTION_LEVEL:g}, read at {rate}): Coulomb "
            "friction? --regressors friction adds such terms (docs/cli.md)")


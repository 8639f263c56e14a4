"""Choosing a structure by how well it predicts or simulates data it was not fitted on.

An in-sample criterion (AIC, BIC, ...) judges a structure on the rows it was
fitted to. *Validated selection* judges it on rows held out:

1. **Blocked folds.** The estimation samples (all segments, in order) are cut
   into K contiguous blocks (:data:`FOLDS`, fewer for short records). Fold i
   fits on the rows whose whole regression window lies outside block i and is
   judged on block i, simulated from the block's own first samples (time
   series are not shuffled: neighbouring samples are not independent).
2. **Candidates.** The GA's best structures by the criterion (the
   short-list), the best structure of every size the search scored (a ladder
   of sizes, so a smaller structure can win when the criterion overfits), and
   the path of forward selection (small structures the GA may never visit).
3. **Score.** The mean over folds of the held-out MSE of the one-step
   prediction (focus prediction) or of the free-run simulation (focus
   simulation; a run that leaves the measured range anywhere rejects the
   structure). Among the structures within one standard error (over folds)
   of the best, the one with the fewest terms is chosen.
4. **Guard** (focus simulation). The chosen structure's model -- fitted on all
   data, refined on its free-run error -- must stay in range off the
   estimation data: on every held-out block, driven by the record's input
   shifted by half its length and reversed in time, and driven by
   :data:`SURROGATES` inputs with the same amplitude spectrum and random
   phases (clipped to the measured range) -- inputs like those it was fitted
   on, in orders the estimation never saw. A model that leaves
   the output's range widened by :data:`STRESS_FACTOR` spans is removed and
   the next candidate tried; the answer counts the structures removed.

The final model is always fitted on all estimation data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..defaults import (
    EXCITED_DIRECTIONS,
    FOLDS,
    INTERLEAVED_PIECES,
    MAX_CANDIDATES,
    MIN_BLOCK_ROWS,
    MIN_FOLD_EXCITATION,
    ONE_SE,
    SIMULATION_FOLDS,
    SIMULATION_REPEATS,
    STRESS_FACTOR,
    SURROGATES,
)
from ..fit.lstsq import reference_fit
from ..model.segments import rows_segments
from ..model.simulation import divergence_bounds, run_model

__all__ = ["FOLDS", "MIN_FOLD_EXCITATION", "SIMULATION_FOLDS", "SIMULATION_REPEATS", "Fold",
           "Scores", "block_splits", "blocked_folds", "candidate_structures", "cv_scores",
           "fold_excitation", "informative_folds", "interleaved_folds", "stress_check",
           "stress_inputs", "sub_blocks", "surrogate_input"]


@dataclass(frozen=True)
class Fold:
    """One fold: what to fit on and the held-out segments to judge on.

    ``train`` marks the problem's rows whose regression window misses the held-out
    block; ``train_segments`` are the same data as sample ranges (the segments
    with the block cut out), for fits on the free-run error.
    """

    train: np.ndarray                      # bool over the problem's rows
    held_out: list[tuple[int, int]]        # sample ranges [start, stop), simulated from start
    train_segments: list[tuple[int, int]]  # the rest of the segments


def blocked_folds(problem, k: int = FOLDS, repeats: int = 1) -> list[Fold]:
    """K contiguous held-out blocks over the problem's segments (fewer if the data are short).

    With ``repeats`` R > 1, the K blocks are laid R times, each time shifted by
    1/R of a block (a block that runs past the end wraps to the start): K * R
    folds, every sample held out R times, in blocks as long as K alone gives
    (long blocks judge long simulations; the repeats steady the estimate).
    Returns an empty list when not even two blocks of :data:`MIN_BLOCK_ROWS`
    held-out rows fit.
    """
    lag = problem.term_space.max_lag
    n = len(problem.y)
    t = problem.row_times
    while k >= 2:
        splits = block_splits(problem.segments, k, repeats, lag)
        folds = []
        for held, rest in splits or []:
            outside = np.ones(len(t), dtype=bool)
            for a, b in held:  # the row's window [t - lag, t] must miss the block
                outside &= (t < a) | (t - lag >= b)
            folds.append(Fold(outside, rows_segments(held, n, lag), rows_segments(rest, n, 0)))
        if folds and all(f.train.sum() > 0 for f in folds):
            return folds
        k -= 1
    return []


def informative_folds(problem, k: int = FOLDS, repeats: int = 1
                      ) -> tuple[list[Fold], str]:
    """Held-out folds whose training rows each see the input's excitation; how they lie.

    Contiguous blocks first (:func:`blocked_folds`: long blocks judge long
    simulations). When a fold's rows do not excite the linear terms as the
    record does (:func:`fold_excitation` below :data:`MIN_FOLD_EXCITATION`: the
    input changes in one place, as in a step test), the record is cut into
    shorter blocks dealt to the folds in turn (:func:`interleaved_folds`), so
    that each fold fits on part of every transient and is judged on the rest.
    When even that fails, no folds, and the reason.

    Returns
    -------
    folds : list of Fold
        Empty when the record cannot be folded.
    note : str
        '' for contiguous blocks; else how the folds lie, or why there are none.
    """
    folds = blocked_folds(problem, k, repeats)
    if not folds:
        return [], "the record is too short for held-out blocks"
    share = fold_excitation(problem, folds)
    if share >= MIN_FOLD_EXCITATION:
        return folds, ""
    for pieces in INTERLEAVED_PIECES:
        alt = interleaved_folds(problem, k, pieces)
        if alt and fold_excitation(problem, alt) >= MIN_FOLD_EXCITATION:
            size = len(problem.y) // (k * pieces)
            return alt, (f"held-out blocks of about {size} samples dealt to {k} folds in turn: "
                         f"in contiguous blocks a fold kept {share:.0%} of the input's "
                         "excitation (the input changes in few places, e.g. a step test)")
    return [], ("the record cannot be cut into held-out blocks that each leave the input's "
                f"excitation to fit on (a fold keeps {share:.0%} of it: the input changes in "
                "one place, e.g. a step test)")



def interleaved_folds(problem, k: int, pieces: int) -> list[Fold]:
    """K folds of ``pieces`` short blocks each: the record's k * pieces blocks dealt in turn.

    Empty when a block would hold no more rows than the largest lag plus
    :data:`MIN_BLOCK_ROWS` / ``pieces`` (too short to judge a simulation on).
    """
    lag = problem.term_space.max_lag
    n = len(problem.y)
    positions = np.concatenate([np.arange(a, b) for a, b in problem.segments])
    edges = np.linspace(0, len(positions), k * pieces + 1).round().astype(int)
    if np.min(np.diff(edges)) <= lag + max(MIN_BLOCK_ROWS // pieces, 2):
        return []
    t = problem.row_times
    folds = []
    for i in range(k):
        block = np.sort(np.concatenate([positions[edges[j]:edges[j + 1]]
                                        for j in range(i, k * pieces, k)]))
        held = _runs(block, problem.segments)
        outside = np.ones(len(t), dtype=bool)
        for a, b in held:
            outside &= (t < a) | (t - lag >= b)
        if not outside.any():
            return []
        rest = _complement(problem.segments, held, lag)
        folds.append(Fold(outside, rows_segments(held, n, lag), rows_segments(rest, n, 0)))
    return folds



def fold_excitation(problem, folds: list[Fold]) -> float:
    """How well the worst fold's training rows excite the linear terms, relative to all rows.

    The linear terms' columns (unit RMS) span directions the record excites;
    those excited at least :data:`EXCITED_DIRECTIONS` as much as the most
    excited one must be excited by each fold's rows too. The measure is the
    smallest ratio, over those directions, of the energy per row on the fold's
    rows to that on all rows (the smallest generalised eigenvalue): about 1 when
    a fold sees the input vary as the whole record does, near 0 when the input
    changes only inside the held-out block (a step test: the block with the
    step holds out all the information about the input's effect, and a fit on
    the rest cannot find it). See :data:`MIN_FOLD_EXCITATION`.
    """
    degree = np.array([len(t) for t in problem.term_space.terms])
    X = problem.columns[:, (degree <= 1) & problem.usable]
    if not folds or X.shape[1] == 0:
        return 1.0
    rms = np.sqrt(np.mean(X * X, axis=0))
    X = X[:, rms > 0] / rms[rms > 0]
    w, V = np.linalg.eigh(X.T @ X / len(X))
    keep = w >= EXCITED_DIRECTIONS * w[-1]
    if not keep.any():
        return 1.0
    Z = (X @ V[:, keep]) / np.sqrt(w[keep])  # the excited directions, whitened on all rows
    worst = 1.0
    for f in folds:
        rows = Z[f.train]
        if not len(rows):
            return 0.0
        worst = min(worst, float(np.linalg.eigvalsh(rows.T @ rows / len(rows))[0]))
    return max(worst, 0.0) ** 0.5


def block_splits(segments, k: int, repeats: int, lag: int
                 ) -> list[tuple[list[tuple[int, int]], list[tuple[int, int]]]] | None:
    """K contiguous blocks over the segments, laid ``repeats`` times: (held out, rest) each.

    The sample ranges of each block (split at gaps and segment borders) and of
    the rest (the parts outside the block longer than the lag). None when a
    block has fewer than :data:`MIN_BLOCK_ROWS` held-out rows.
    """
    positions = np.concatenate([np.arange(a, b) for a, b in segments]) if len(segments) \
        else np.empty(0, dtype=int)
    edges = np.linspace(0, len(positions), k + 1).round().astype(int)
    out = []
    for r in range(repeats):
        shift = int(round(r * len(positions) / (k * repeats)))
        rolled = np.roll(positions, -shift)
        for i in range(k):
            held = _runs(np.sort(rolled[edges[i]:edges[i + 1]]), segments)
            if sum(max(b - a - lag, 0) for a, b in held) < MIN_BLOCK_ROWS:
                return None
            out.append((held, _complement(segments, held, lag)))
    return out


def sub_blocks(problem, folds: list[Fold]) -> np.ndarray:
    """Each sample's sub-block: the record cut into as many equal parts as there are folds.

    With repeated blocks every sub-block is held out by the same number of folds
    and never fitted on by them, so the sub-blocks' held-out errors are separate
    estimates, one per sub-block (-1 outside the segments). When each sample is
    held out by one fold only (interleaved folds), its sub-block is that fold.
    """
    label = np.full(len(problem.y), -1, dtype=int)
    held = np.zeros(len(problem.y), dtype=int)
    for i, fold in enumerate(folds):
        for a, b in fold.held_out:
            label[a:b] = i
            held[a:b] += 1
    if held.max(initial=0) <= 1:  # each sample held out once (interleaved): by its fold
        return label
    positions = np.concatenate([np.arange(a, b) for a, b in problem.segments])
    label[:] = -1
    label[positions] = np.arange(len(positions)) * len(folds) // len(positions)
    return label


def _complement(segments, held, lag: int) -> list[tuple[int, int]]:
    """The parts of the segments outside the held-out ranges (longer than the lag)."""
    out = []
    for a, b in segments:
        cuts = sorted((max(c, a), min(d, b)) for c, d in held if c < b and d > a)
        start = a
        for c, d in cuts:
            if c - start > lag:
                out.append((start, c))
            start = max(start, d)
        if b - start > lag:
            out.append((start, b))
    return out


def _runs(block: np.ndarray, segments) -> list[tuple[int, int]]:
    """The sample ranges of a block (sorted positions), split at gaps and segment borders."""
    out = []
    for a, b in segments:
        inside = block[(block >= a) & (block < b)]
        if inside.size:
            cuts = np.flatnonzero(np.diff(inside) != 1) + 1
            for part in np.split(inside, cuts):
                out.append((int(part[0]), int(part[-1]) + 1))
    return out


@dataclass
class Scores:
    """Validated scores of structures: mean held-out MSE and its standard error."""

    masks: list[np.ndarray] = field(default_factory=list)
    mean: list[float] = field(default_factory=list)
    stderr: list[float] = field(default_factory=list)
    rejected: int = 0  # structures whose held-out simulation left the range

    def best(self) -> int | None:
        """Index of the chosen structure: fewest terms within one SE of the lowest mean."""
        finite = [i for i, v in enumerate(self.mean) if np.isfinite(v)]
        if not finite:
            return None
        low = min(finite, key=lambda i: self.mean[i])
        limit = self.mean[low] + ONE_SE * self.stderr[low]
        near = [i for i in finite if self.mean[i] <= limit]
        return min(near, key=lambda i: (int(self.masks[i].sum()), self.mean[i]))

    def order(self) -> list[int]:
        """Indices by the selection rule: the chosen first, then by mean."""
        first = self.best()
        rest = sorted((i for i, v in enumerate(self.mean) if np.isfinite(v) and i != first),
                      key=lambda i: self.mean[i])
        return ([first] if first is not None else []) + rest


def cv_scores(problem, folds: list[Fold], masks, simulate: bool,
              horizon: int | None = None) -> Scores:
    """Validated scores of structures (masks over the whole term space).

    ``simulate``: the held-out free run, or with ``horizon`` the k-step prediction.
    """
    out = Scores()
    for mask in masks:
        values = [_fold_mse(problem, f, mask, simulate, horizon) for f in folds]
        out.masks.append(np.asarray(mask, dtype=bool))
        if not all(np.isfinite(values)):
            out.mean.append(np.inf)
            out.stderr.append(np.inf)
            out.rejected += bool(simulate and any(v == np.inf for v in values))
            continue
        out.mean.append(float(np.mean(values)))
        out.stderr.append(float(np.std(values, ddof=1) / np.sqrt(len(values)))
                          if len(values) > 1 else 0.0)
    return out


def _fold_mse(problem, fold: Fold, mask: np.ndarray, simulate: bool,
              horizon: int | None = None) -> float:
    """Held-out MSE of the structure fitted on the fold's training rows (inf: unusable)."""
    mask = np.asarray(mask, dtype=bool)
    train = fold.train
    if not mask.any() or (mask & ~problem.usable).any() or train.sum() <= mask.sum():
        return np.nan
    fit = reference_fit(problem.columns[train], problem.target[train], mask)
    if fit.rank_deficient:
        return np.nan
    theta = fit.coefficients  # on the scaled problem
    ts = problem.term_space
    lag = ts.max_lag
    if not simulate:
        held = np.zeros(len(train), dtype=bool)
        t = problem.row_times
        for a, b in fold.held_out:
            held |= (t >= a + lag) & (t < b)
        e = problem.target[held] - problem.columns[held][:, mask] @ theta
        return float(np.mean(e * e)) * problem.sse_scale
    model = _scaled_model(problem, mask, theta)
    u = problem.u / problem.u_scale
    y = problem.y / problem.y_scale
    bounds = divergence_bounds(y)
    sse, rows = 0.0, 0
    for a, b in fold.held_out:
        yhat, at = run_model(model.compiled, theta, u[a:b], y[a:b], horizon, bounds)
        if at is not None:
            return np.inf
        e = y[a + lag:b] - yhat
        sse += float(e @ e)
        rows += len(e)
    return sse / rows * problem.sse_scale


def _scaled_model(problem, mask, theta):
    from ..model.narx import NarxModel

    return NarxModel(problem.term_space, [int(i) for i in np.flatnonzero(mask)], theta)


def stress_check(model, u: np.ndarray, y: np.ndarray, segments) -> str | None:
    """Why the model's simulation is not bounded off the estimation data, or None.

    Its free run on every segment, and driven by each segment's input shifted
    by half its length, reversed in time and with its phases randomised
    (:data:`SURROGATES` draws, :func:`surrogate_input`), from the segment's own
    initial outputs, must stay inside the measured output's range widened by
    :data:`STRESS_FACTOR` spans.
    """
    y = np.asarray(y, dtype=float)
    lo, hi = float(np.min(y)), float(np.max(y))
    span = max(hi - lo, 1e-300)
    bounds = (lo - STRESS_FACTOR * span, hi + STRESS_FACTOR * span)
    u2 = model.term_space.inputs_2d(u)
    lag = model.term_space.max_lag
    for a, b in segments:
        if b - a <= lag:
            continue
        seg_y = y[a:b]
        for label, uu in stress_inputs(u2[a:b]):
            yy = seg_y.copy()
            yy[lag:] = 0.0  # only the initial conditions are measured
            yhat, at = run_model(model.compiled, model.coefficients, uu, yy, None, bounds)
            if at is not None or not np.all(np.isfinite(yhat)):
                return f"its simulation driven by {label} left the output's range"
    return None


def stress_inputs(u: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The guard's inputs for one segment's input ``u`` (n, m), each with its description.

    The input itself, shifted by half its length, reversed in time, and
    :data:`SURROGATES` random-phase inputs like it (fixed seed: repeatable).
    """
    rng = np.random.default_rng(0)
    out = [("the estimation input", u),
           ("the input shifted by half its length", np.roll(u, len(u) // 2, axis=0)),
           ("the input reversed in time", u[::-1])]
    out += [(f"an input with the estimation input's spectrum and random phases "
             f"(draw {i + 1} of {SURROGATES})", surrogate_input(u, rng))
            for i in range(SURROGATES)]
    return out


def surrogate_input(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An input like ``u`` (n, m): each column's amplitude spectrum, random phases.

    The result is clipped to each column's measured range, so it excites the
    model at the frequencies and amplitudes of the estimation data but in an
    order the estimation never saw (a second multisine phase draw, a second run
    of a random signal).
    """
    out = np.empty_like(u, dtype=float)
    n = len(u)
    for j in range(u.shape[1]):
        col = u[:, j]
        mean = col.mean()
        spectrum = np.fft.rfft(col - mean)
        phases = rng.uniform(0.0, 2.0 * np.pi, len(spectrum))
        phases[0] = 0.0
        if n % 2 == 0:
            phases[-1] = 0.0  # the Nyquist bin stays real
        out[:, j] = np.clip(np.fft.irfft(np.abs(spectrum) * np.exp(1j * phases), n) + mean,
                            col.min(), col.max())
    return out


def candidate_structures(problem, evaluator, shortlist: int, forward: Callable | None = None,
                         max_candidates: int = MAX_CANDIDATES) -> np.ndarray:
    """Masks (whole term space) to judge: the short-list, a ladder of sizes, forward path.

    ``forward`` returns forward selection's path (masks over the usable columns).
    """
    sets = [evaluator.ranked(shortlist)]
    each = max(2, (max_candidates - shortlist) // 2)
    for ladder in (evaluator.best_per_size(), forward() if forward is not None else None):
        if ladder is None or not len(ladder):
            continue
        if len(ladder) > each:  # sizes spread over the whole range
            pick = np.unique(np.linspace(0, len(ladder) - 1, each).round()).astype(int)
            ladder = ladder[pick]
        sets.append(ladder)
    masks = np.concatenate([s for s in sets if len(s)]) if any(len(s) for s in sets) \
        else np.zeros((0, evaluator.n_terms), dtype=bool)
    if not len(masks):
        return np.zeros((0, problem.term_space.n_terms), dtype=bool)
    masks = np.unique(masks, axis=0)
    return problem.expand(masks)

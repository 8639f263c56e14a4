"""Held-out blocks of a record: where a structure is fitted and where it is judged.

The estimation samples (all segments, in order) are cut into K contiguous
blocks (:func:`blocked_folds`, laid R times shifted for the simulation focus).
Fold i fits on the rows whose whole regression window lies outside block i and
is judged on block i, simulated from the block's own first samples (time series
are not shuffled: neighbouring samples are not independent). A fold must see the
input vary as the record does (:func:`fold_excitation`); when the input changes
in few places (a step test), short blocks are dealt to the folds in turn
(:func:`interleaved_folds`), and a record that cannot be folded says so
(:func:`informative_folds`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import (
    EXCITED_DIRECTIONS,
    FACTOR_SLICE_BYTES,
    FINAL_JACOBIAN_BYTES,
    FOLDS,
    INTERLEAVED_PIECES,
    JOINT_JACOBIAN_BYTES,
    LONG_FINAL_STEPS,
    LONG_ROWS,
    LONG_SUB_BLOCKS,
    MIN_BLOCK_ROWS,
    MIN_FOLD_EXCITATION,
    REFINE_ROWS,
    REFINE_WINDOWS,
)
from ..model.segments import rows_segments

__all__ = ["Fold", "block_splits", "blocked_folds", "final_samples", "final_steps",
           "windowed_rows",
           "fold_excitation", "informative_folds", "interleaved_folds", "is_long",
           "refinement_windows", "sub_blocks"]


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
    degree = problem.term_space.term_degrees
    cols = np.flatnonzero((degree <= 1) & problem.usable)
    if not folds or len(cols) == 0:
        return 1.0
    P = problem.columns  # its linear columns' Gram matrices, a slice of rows at a time
    at = problem.column_index(cols)
    step = max(1, FACTOR_SLICE_BYTES // (8 * len(cols)))
    gram = np.zeros((len(cols), len(cols)))
    grams = np.zeros((len(folds), len(cols), len(cols)))
    for a in range(0, P.shape[0], step):
        X = P[a:a + step][:, at]
        gram += X.T @ X
        for g, f in zip(grams, folds):
            part = X[f.train[a:a + step]]
            g += part.T @ part
    n = P.shape[0]
    rms = np.sqrt(np.diag(gram) / n)
    live = rms > 0
    scale = 1.0 / rms[live]
    w, V = np.linalg.eigh(scale[:, None] * gram[np.ix_(live, live)] * scale / n)
    keep = w >= EXCITED_DIRECTIONS * w[-1]
    if not keep.any():
        return 1.0
    T = scale[:, None] * V[:, keep] / np.sqrt(w[keep])  # the excited directions, whitened
    worst = 1.0
    for g, f in zip(grams, folds):
        count = int(f.train.sum())
        if not count:
            return 0.0
        worst = min(worst, float(np.linalg.eigvalsh(T.T @ g[np.ix_(live, live)] @ T / count)[0]))
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


def is_long(problem) -> bool:
    """A long record (:data:`~spm_sysid.core.defaults.LONG_ROWS`): blocks laid once, cut."""
    return problem.rows > LONG_ROWS


def final_steps(problem) -> dict:
    """The final refinement's limit: ``{}`` (its own), or a long record's (keywords)."""
    return {"max_evaluations": LONG_FINAL_STEPS} if is_long(problem) else {}


def sub_blocks(problem, folds: list[Fold]) -> np.ndarray:
    """Each sample's sub-block: separate held-out estimates for the paired test.

    With repeated blocks, the record cut into as many equal parts as there are
    folds: every sub-block is held out by the same number of folds and never
    fitted on by them, so the sub-blocks' held-out errors are separate
    estimates, one per sub-block (-1 outside the segments). When each sample is
    held out by one fold only, its sub-block is that fold; on a long record
    (:func:`is_long`) each fold's held-out samples are cut in
    :data:`~spm_sysid.core.defaults.LONG_SUB_BLOCKS` consecutive parts.
    """
    label = np.full(len(problem.y), -1, dtype=int)
    held = np.zeros(len(problem.y), dtype=int)
    for i, fold in enumerate(folds):
        for a, b in fold.held_out:
            label[a:b] = i
            held[a:b] += 1
    if held.max(initial=0) <= 1:  # each sample held out once: by its fold
        if is_long(problem):
            for i, fold in enumerate(folds):
                at = np.concatenate([np.arange(a, b) for a, b in fold.held_out])
                label[at] = i * LONG_SUB_BLOCKS + (
                    np.arange(len(at)) * LONG_SUB_BLOCKS // max(len(at), 1))
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


def final_samples(segments, lag: int, row_bytes: int, single: bool = False
                  ) -> list[tuple[int, int]]:
    """The samples a final refinement fits on: every one while its Jacobian fits.

    ``row_bytes``: the Jacobian's bytes per row. Beyond
    :data:`~spm_sysid.core.defaults.JOINT_JACOBIAN_BYTES` (the joint refinement of
    several outputs holds about four such arrays), or
    :data:`~spm_sysid.core.defaults.FINAL_JACOBIAN_BYTES` for a ``single``
    output's, it fits on windows spread over the record
    (:func:`refinement_windows`) of as many rows as fit.
    """
    budget = FINAL_JACOBIAN_BYTES if single else JOINT_JACOBIAN_BYTES
    segments = [(int(a), int(b)) for a, b in segments]
    if sum(b - a for a, b in segments) * row_bytes <= budget:
        return segments
    return refinement_windows(segments, lag, rows=budget // row_bytes)


def windowed_rows(samples, segments, lag: int) -> int | None:
    """The rows of ``segments`` that ``samples`` from :func:`final_samples` stand for.

    None when the samples are the segments themselves (every row); else every
    row's count, which a covariance from the windows is scaled to.
    """
    if [(int(a), int(b)) for a, b in samples] == [(int(a), int(b)) for a, b in segments]:
        return None
    return sum(max(int(b) - int(a) - lag, 0) for a, b in segments)


def refinement_windows(segments, lag: int, rows: int = REFINE_ROWS,
                       windows: int = REFINE_WINDOWS) -> list[tuple[int, int]]:
    """The samples a refinement fits on: ``segments`` whole, or windows spread over them.

    A record of at most ``rows`` samples is used whole (nothing changes for it).
    A longer one gives ``windows`` windows of ``rows / windows`` samples each,
    evenly spread over its samples (in order, split at segment borders; each
    longer than ``lag``): the refinement sees the whole record's range of
    inputs, at a cost that does not grow with the record.
    """
    segments = [(int(a), int(b)) for a, b in segments]
    total = sum(b - a for a, b in segments)
    if total <= rows:
        return segments
    positions = np.concatenate([np.arange(a, b) for a, b in segments])
    size = rows // windows
    starts = np.linspace(0, len(positions) - size, windows).round().astype(int)
    block = np.unique(np.concatenate([positions[s:s + size] for s in starts]))
    return [(a, b) for a, b in _runs(block, segments) if b - a > lag]

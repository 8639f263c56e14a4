"""Decimation: a record sampled faster than its dynamics, taken to a slower rate.

A joint sampled at 1 kHz moves little between two samples, so its measured
position's second difference (what an equation-error fit of a position model
explains) is mostly encoder noise, and least squares on lagged noisy outputs
is biased: the friction and input coefficients come out wrong by factors.
Taking every ``factor``-th sample makes the motion between samples ``factor``
squared times larger against the same noise.

How a block of ``factor`` samples becomes one sample (the same in a record,
:func:`decimate_blocks`, and in a stream, :class:`BlockDecimator`):

* the **inputs** are averaged over the block: a torque held sample by sample
  acts over the block as its mean does (the held input's equivalent);
* the **outputs** are the block's first sample: a measurement, not a filtered
  one, so the model's equation holds between measured values, and the block's
  inputs act after it (delay 1 stays delay 1).

Blocks never cross a segment's end; the samples at a segment's end too few for
a block are not used and counted. A model identified on a decimated record
runs on records decimated the same way: its document says so
(``metadata.decimation``, docs/model_format.md), and ``validate`` and the
node's monitor decimate what they read by it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BlockDecimator", "compose", "decimate_blocks", "decimation_doc",
           "decimation_factor", "decimation_phrase", "describe_decimation"]

#: How a block becomes one sample, in the document's words.
INPUTS_RULE = "mean over the block"
OUTPUTS_RULE = "first sample of the block"


def decimate_blocks(u: np.ndarray, y: np.ndarray, bounds: list[tuple[int, int]],
                    factor: int) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]],
                                          np.ndarray]:
    """The samples of ``bounds`` decimated by ``factor``, segment by segment.

    Parameters
    ----------
    u : ndarray, shape (n,) or (n, m)
        Inputs: averaged over each block.
    y : ndarray, shape (n,) or (n, q)
        Outputs: each block's first sample.
    bounds : list of (start, stop)
        Contiguous segments; blocks stay inside them.
    factor : int
        Samples per block (>= 1).

    Returns
    -------
    u_d, y_d : ndarray
        One sample per whole block: the block's mean input, its first output.
    bounds_d : list of (start, stop)
        The segments in the decimated samples (one per input segment, possibly empty).
    first : ndarray of int
        The index in ``u, y`` of each decimated sample's block start (stamps, rows).
    """
    if factor < 1:
        raise ValueError(f"the decimation factor must be >= 1, got {factor}")
    us, ys, firsts, out, start = [], [], [], [], 0
    for a, b in bounds:
        blocks = (b - a) // factor
        stop = a + blocks * factor
        us.append(u[a:stop].reshape((blocks, factor) + u.shape[1:]).mean(axis=1))
        ys.append(y[a:stop:factor])
        firsts.append(np.arange(a, stop, factor))
        out.append((start, start + blocks))
        start += blocks
    empty_u, empty_y = u[:0], y[:0]
    return (np.concatenate(us) if us else empty_u, np.concatenate(ys) if ys else empty_y,
            out, np.concatenate(firsts) if firsts else np.zeros(0, dtype=int))


def decimation_doc(factor: int, samples: int, kept: int, in_segments: int) -> dict:
    """What a model document records of a decimation (``metadata.decimation``).

    ``samples`` recorded, ``kept`` blocks, ``in_segments`` samples inside the
    segments (those of them no block took are ``unused``).
    """
    return {"factor": int(factor), "samples": int(samples), "kept": int(kept),
            "unused": int(in_segments - kept * factor), "inputs": INPUTS_RULE,
            "outputs": OUTPUTS_RULE}


def compose(earlier: dict, later: dict) -> dict:
    """Two decimations one after the other, as one decimation.

    Blocks of ``a`` then of ``b`` are blocks of ``a b``: a mean of equal means is
    the mean, a first of firsts is the first.
    """
    factor = int(earlier["factor"]) * int(later["factor"])
    return {**later, "factor": factor, "samples": earlier["samples"],
            "unused": earlier["unused"] + later["unused"] * int(earlier["factor"])}


def decimation_factor(metadata: Any) -> int:
    """The factor a model document says its model runs at (1: the record's own rate)."""
    doc = metadata.get("decimation") if isinstance(metadata, dict) else None
    return int(doc.get("factor", 1)) if isinstance(doc, dict) else 1


def describe_decimation(doc: dict | None) -> str:
    """The decimation in words ('' when there was none)."""
    if not doc or int(doc.get("factor", 1)) <= 1:
        return ""
    text = (f"decimated by {doc['factor']}: {doc['samples']} samples to {doc['kept']} "
            f"(inputs: {doc.get('inputs', INPUTS_RULE)}; outputs: "
            f"{doc.get('outputs', OUTPUTS_RULE)})")
    if doc.get("unused"):
        text += (f"; {doc['unused']} sample(s) at segment ends, too few for a block, "
                 "not used")
    return text


def decimation_phrase(doc: dict | None) -> str:
    """The decimation in a clause for one-line answers ('' when there was none)."""
    if not doc or int(doc.get("factor", 1)) <= 1:
        return ""
    unused = f", {doc['unused']} unused at segment ends" if doc.get("unused") else ""
    return f" (decimated by {doc['factor']} from {doc['samples']} samples{unused})"


class BlockDecimator:
    """The decimation of :func:`decimate_blocks`, one sample at a time (the node's stream).

    :meth:`push` takes each sample and returns the decimated one when its block
    is complete (None before); :meth:`reset` drops a partial block (a gap).
    """

    def __init__(self, factor: int) -> None:
        if factor < 1:
            raise ValueError(f"the decimation factor must be >= 1, got {factor}")
        self.factor = int(factor)
        self.dropped = 0  # samples of partial blocks given up at gaps
        self._count, self._sum, self._first = 0, 0.0, None

    def reset(self) -> None:
        """Start a new block (the samples of a partial one are counted in ``dropped``)."""
        self.dropped += self._count
        self._count, self._sum, self._first = 0, 0.0, None

    def push(self, stamp_ns: int, u, y) -> tuple[int, Any, Any] | None:
        """The decimated ``(stamp, u, y)`` when this sample completes a block, else None."""
        u = np.asarray(u, dtype=float)
        if self._count == 0:
            self._first, self._sum = (stamp_ns, y), u.copy()
        else:
            self._sum = self._sum + u
        self._count += 1
        if self._count < self.factor:
            return None
        mean = self._sum / self.factor
        stamp, first_y = self._first
        self._count, self._sum, self._first = 0, 0.0, None
        return stamp, (float(mean) if mean.ndim == 0 else mean), first_y

"""An output that repeats each value for a fixed number of samples: a slower sensor, held.

A log that merges topics at the fastest one's rate (a CSV export, a message
filter, a ``/joint_states`` at 1 kHz carrying an encoder read at 100 Hz) holds
each slow sample until the next: the output then stays exactly equal for runs
of about the same length L and jumps between them. A model of those samples
learns the hold, not the plant: its lagged outputs are mostly copies of the
current one. Measured (a second-order plant read every 10th sample and held,
the command as typed): free run 0.424 on a new record where the plant's noise
is 0.002, against the linear ARX's 1.05, and no word of why. At the sensor's
instants 0.227, and 0.143 at its rate (``--decimate 10``: each block's first
output is a fresh sample; the block's mean input loses what the input did within
the block): better, not good. A model of the plant at the record's rate from an
output seen every L-th sample would need a fit with missing outputs, which this
package does not make.

:func:`held_output` reads the runs of exactly equal consecutive values in each
segment. It is a hold when most steps are zero (:data:`HELD_SHARE`), the
median run is two samples or more, and the runs are regular: :data:`REGULAR`
of them as long as their mean rounded down or up (3 and 4 samples for a
30 Hz sensor in a 100 Hz log), or one sample more or less where the mean is
4 or more (a log merged by stamps that jitter). A quantized output (an encoder, an ADC at rest)
also repeats values, in runs of irregular lengths; an output clipped at an end
holds one value, in runs of any length: neither is said here. The sensor's
rate is the record's over the mean run length; the advice is ``--decimate``
by that ratio rounded (outputs are read at each block's first sample, so a
held value is read once).

Only the output is read: an input held between commands is what the plant
receives (a zero-order hold), and a model of it is right.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HELD_SHARE", "HeldOutput", "REGULAR", "describe_held_output", "held_output"]

#: Share of the output's steps that must be exactly zero ...
HELD_SHARE = 0.5

#: ... and share of its runs as long as their mean, rounded down or up.
REGULAR = 0.9

#: Fewest runs (changes of value) that make a statement.
MIN_RUNS = 20


@dataclass(frozen=True)
class HeldOutput:
    """Runs of equal output values (:func:`held_output`)."""

    zero_steps: float   # share of the steps that are exactly zero
    runs: int           # runs counted (each segment's first and last left out)
    median: int         # median run length (samples)
    mean: float         # mean run length: the record's rate over the sensor's
    regular: float      # share of the runs of the mean's length (see the module doc)

    @property
    def held(self) -> bool:
        return (self.zero_steps >= HELD_SHARE and self.median >= 2
                and self.regular >= REGULAR)


def held_output(y: np.ndarray, segments=None) -> HeldOutput | None:
    """The runs of exactly equal consecutive values of ``y`` over its segments.

    None when there are fewer than :data:`MIN_RUNS` complete runs (a run cut by
    a segment's start or end is left out, as is a run holding NaN).
    """
    y = np.asarray(y, dtype=float)
    parts = [y[a:b] for a, b in segments] if segments else [y]
    lengths, steps, zero = [], 0, 0
    for part in parts:
        if len(part) < 2:
            continue
        same = part[1:] == part[:-1]
        steps += len(same)
        zero += int(np.count_nonzero(same))
        change = np.flatnonzero(~same) + 1  # where a new value starts
        if len(change) >= 2:
            runs = np.diff(change)
            starts = change[:-1]
            finite = np.isfinite(part[starts])
            lengths.append(runs[finite])
    runs = np.concatenate(lengths) if lengths else np.zeros(0, dtype=int)
    if len(runs) < MIN_RUNS or steps == 0:
        return None
    median, mean = int(np.median(runs)), float(np.mean(runs))
    slack = 1 if mean >= 4 else 0  # a log merged by stamps shifts a longer run by one
    regular = float(np.mean((runs >= np.floor(mean) - slack) & (runs <= np.ceil(mean) + slack)))
    return HeldOutput(zero / steps, len(runs), median, mean, regular)


def describe_held_output(found: HeldOutput | None, name: str = "y") -> str:
    """The data check's warning for a held output ('' when it is not held)."""
    if found is None or not found.held:
        return ""
    ratio = found.mean
    step = round(ratio)
    advice = (f"log the sensor at its own rate, or identify at it: --decimate {step} "
              "(docs/cli.md)" if abs(ratio - step) <= 0.1 * step else
              f"log the sensor at its own rate (about 1/{ratio:.1f} of the record's), or "
              f"try --decimate {max(int(ratio), 2)} (docs/cli.md)")
    return (f"output {name} repeats each value for about {ratio:.1f} samples "
            f"({found.zero_steps:.0%} of its steps are zero, {found.regular:.0%} of its "
            f"{found.runs} runs {_lengths(found.mean)} samples long): it was measured "
            f"about {ratio:.1f}x slower than the record's rate and held (a slower sensor "
            "merged into a faster log?); a model of the held samples describes the hold, "
            f"not the plant: {advice}")


def _lengths(mean: float) -> str:
    slack = 1 if mean >= 4 else 0
    low, high = int(np.floor(mean)) - slack, int(np.ceil(mean)) + slack
    return str(low) if low == high else f"{low} or {high}" if high == low + 1 else \
        f"{low} to {high}"

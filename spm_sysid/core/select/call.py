"""The one linear/nonlinear call: a nonlinear model replaces the best linear one only on proof.

Off the estimation data a linear model often simulates as well as a nonlinear
one that fits the estimation data better. So the best linear finalist (lowest
mean held-out error) is the default; a nonlinear finalist replaces it only when
it simulates the held-out blocks better by more than the noise of that
comparison: over the blocks, the log ratio ``ln(error_linear / error_nonlinear)``
has a positive mean with a one-sided paired t-test p-value below
:data:`~spm_sysid.core.defaults.SIGNIFICANCE` (blocks differ a lot in level; the
log ratio compares each block with itself). One nonlinear finalist is tested --
the fewest terms within one standard error of the best nonlinear one -- since
testing each of many would pass one by chance.

Single-output selection (:mod:`spm_sysid.core.select.finalists`) and the coupled
judgement of several outputs (:mod:`spm_sysid.core.select.coupled`) both decide
with :func:`linear_or_nonlinear`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..defaults import FALLBACKS, SIGNIFICANCE

__all__ = ["Call", "linear_or_nonlinear", "paired_p_value"]


@dataclass(frozen=True)
class Call:
    """The call's outcome over the finalists (indices into the caller's lists).

    Attributes
    ----------
    order : list of int
        The finalists in the order to try them (the choice first; the next ones
        when the guard removes it: after a nonlinear choice, up to
        :data:`~spm_sysid.core.defaults.FALLBACKS` other nonlinear finalists that
        pass the same test, then the best linear one).
    choice : str
        ``linear`` or ``nonlinear``.
    linear : int or None
        The best linear finalist (None: none simulated every block).
    challenger : int or None
        The nonlinear finalist tested against it (None: none was better on average).
    ratio, p_value : float or None
        The challenger's mean error over the linear one's, and the test's p-value.
    """

    order: list[int]
    choice: str
    linear: int | None = None
    challenger: int | None = None
    ratio: float | None = None
    p_value: float | None = None


def paired_p_value(reference: Sequence[float], other: Sequence[float]) -> float:
    """One-sided paired t-test over blocks that ``other``'s errors are lower than ``reference``'s.

    On the log ratio of each block's two errors (blocks differ a lot in level; the
    ratio compares each block with itself); errors below 1e-12 of the largest count
    as that floor (a noise-free fit). 0 or 1 when the ratios do not vary.

    Student's t distribution from :func:`scipy.special.stdtr` (the p-value of
    ``scipy.stats.ttest_1samp(d, 0, alternative="greater")``): it spares each
    command the import of scipy.stats (0.5-0.9 s, more than judging a small record).
    """
    from scipy.special import stdtr

    # errors a million millions below the larger are rounding: a perfect fit is not
    # "noisy" because 1e-30 and 1e-33 differ by a factor of a thousand
    floor = max(1e-300, 1e-12 * float(np.max(np.r_[reference, other])))
    d = np.log(np.maximum(reference, floor)) - np.log(np.maximum(other, floor))
    if len(d) < 2 or np.ptp(d) == 0:
        return 0.0 if np.all(d > 0) else 1.0
    t = float(np.mean(d)) / (float(np.std(d, ddof=1)) / np.sqrt(len(d)))
    return float(stdtr(len(d) - 1, -t))


def _one_se_order(mean, stderr, terms, finite) -> list[int]:
    """Fewest terms within one standard error of the lowest mean first, then by mean."""
    if not finite:
        return []
    low = min(finite, key=lambda i: mean[i])
    near = [i for i in finite if mean[i] <= mean[low] + stderr[low]]
    first = min(near, key=lambda i: (terms[i], mean[i]))
    return [first] + sorted((i for i in finite if i != first), key=lambda i: mean[i])


def linear_or_nonlinear(mean: Sequence[float], stderr: Sequence[float],
                        terms: Sequence[int], linear: Sequence[bool],
                        blocks: Sequence[Sequence[float]]) -> Call:
    """The call over finalists (see the module doc).

    Parameters
    ----------
    mean, stderr : sequence of float
        Each finalist's mean held-out error and its standard error (inf: it
        diverged or could not be fitted on a block).
    terms : sequence of int
        Each finalist's number of terms.
    linear : sequence of bool
        Whether each finalist is linear.
    blocks : sequence of sequences of float
        Each finalist's errors per held-out block (the paired test's pairs).
    """
    finite = [i for i, v in enumerate(mean) if np.isfinite(v)]
    lin = [i for i in finite if linear[i]]
    if not lin:
        return Call(_one_se_order(mean, stderr, terms, finite), "nonlinear")
    best = min(lin, key=lambda i: mean[i])
    rest = sorted(finite, key=lambda i: mean[i])
    nonlinear = [i for i in rest if not linear[i]]
    challenger = ratio = p = None
    if nonlinear and mean[nonlinear[0]] < mean[best]:
        low = nonlinear[0]
        near = [i for i in nonlinear if mean[i] <= mean[low] + stderr[low]
                and mean[i] < mean[best]]
        challenger = min(near, key=lambda i: (terms[i], mean[i]))
        ratio = mean[challenger] / mean[best]
        p = paired_p_value(blocks[best], blocks[challenger])
    if challenger is not None and p < SIGNIFICANCE:
        # if the guard removes the challenger: the other nonlinear finalists that beat the
        # best linear one by the same test, then the linear ones
        also = [i for i in nonlinear if i != challenger and mean[i] < mean[best]
                and paired_p_value(blocks[best], blocks[i]) < SIGNIFICANCE][:FALLBACKS]
        order = [challenger] + also + [best] + [i for i in rest
                                                if i not in (challenger, best, *also)]
        return Call(order, "nonlinear", best, challenger, ratio, p)
    order = [best] + [i for i in rest if i != best and linear[i]] + nonlinear
    return Call(order, "linear", best, challenger, ratio, p)

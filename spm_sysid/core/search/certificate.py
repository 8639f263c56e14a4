"""The outcome of a certification, and what the criterion's form gives it.

:class:`Certificate` is what :func:`~spm_sysid.core.search.certify.certify`
returns; :func:`penalty_per_size` checks that a criterion is ``N ln(SSE/N) +
pen(k)`` (what makes a certificate possible) and gives ``pen``; the bounds
read a value back as one-step MSE.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..files import json_float
from ..fit.criteria import CERTIFIABLE, Criterion

__all__ = ["Certificate", "describe_certificate", "mse_bounds", "penalty_per_size",
           "trivial_bound"]


@dataclass
class Certificate:
    """Outcome of :func:`certify`.

    Attributes
    ----------
    status : str
        ``optimal`` (proved) or ``limit`` (the time or node limit ran out).
    value : float
        Criterion value of the best structure found.
    lower_bound : float
        No structure scores below this (``value`` itself when optimal).
    mask : ndarray of bool
        The best structure found.
    nodes : int
        Branch-and-bound nodes explored.
    seconds : float
    bound : str
        The bounds used.
    reason : str or None
        What ran out (``limit``).
    warm_start : float or None
        The warm start's value (e.g. the GA's best).
    one_step_mse : float or None
        The best structure's one-step mean squared error (the data's units).
    mse_lower_bound : float or None
        No structure of at most as many terms has a one-step MSE below this: the
        lower bound read at the best structure's size (``one_step_mse`` itself when
        optimal). For AIC, AICc and BIC ``value = N ln(MSE) + pen(k)``, so it is
        ``one_step_mse * exp(-gap / N)``.
    weakest : list of WeakNode
        When asked (``explain``) and not proved: the weakest open nodes, bounded
        again size by size (:mod:`.explain`).
    """

    status: str
    value: float
    lower_bound: float
    mask: np.ndarray
    nodes: int
    seconds: float
    bound: str = "exact small sizes + drop and pair bounds + span bound (nearly dependent terms)"
    reason: str | None = None
    warm_start: float | None = None
    terms: list[str] = field(default_factory=list)
    one_step_mse: float | None = None
    mse_lower_bound: float | None = None
    weakest: list = field(default_factory=list)

    @property
    def gap(self) -> float:
        """``value - lower_bound`` (0 when optimal)."""
        return 0.0 if self.status == "optimal" else float(self.value - self.lower_bound)

    @property
    def improved(self) -> bool:
        """The search found a better structure than the warm start."""
        return self.warm_start is not None and self.value < self.warm_start - 1e-9

    def to_dict(self) -> dict:
        """JSON-ready (the ``certify --json`` document and ``metadata.certificate``)."""
        return {"status": self.status, "value": float(self.value),
                "lower_bound": float(self.lower_bound), "gap": float(self.gap),
                "terms": list(self.terms), "nodes": int(self.nodes),
                "seconds": round(float(self.seconds), 4), "bound": self.bound,
                "reason": self.reason, "warm_start": self.warm_start,
                "size": int(np.count_nonzero(self.mask)),
                "one_step_mse": json_float(self.one_step_mse),
                "mse_lower_bound": json_float(self.mse_lower_bound),
                **({"weakest": [w.to_dict() for w in self.weakest]} if self.weakest else {})}


def describe_certificate(doc: dict | None) -> str:
    """A certificate in a few words, for answers, logs and the command line ('' if none).

    ``doc`` is :meth:`Certificate.to_dict` (``model.metadata["certificate"]``).
    """
    if not doc:
        return ""
    if doc["status"] == "optimal":
        text = (f"certified optimal over all structures ({doc['nodes']} nodes, "
                f"{doc['seconds']:.2f} s)")
    elif doc["status"] == "limit":
        text = (f"NOT certified ({doc['reason']}): lower bound {doc['lower_bound']:.2f}, "
                f"gap {doc['gap']:.2f}")
        mse, low = doc.get("one_step_mse"), doc.get("mse_lower_bound")
        if mse and low is not None:
            text += (f"; one-step MSE {mse:.4g}: no structure of at most {doc['size']} terms "
                     f"below {low:.4g} (at most {100.0 * (1.0 - low / mse):.1f} % lower)")
    else:
        return f"not certifiable: {doc['reason']}"
    if doc.get("ga_value") is not None and doc["value"] < doc["ga_value"]:
        text += f"; the search improved on the GA's {doc['ga_value']:.2f}"
    elif doc.get("warm_start") is not None and doc["value"] < doc["warm_start"] - 1e-9:
        text += f"; improved on the warm start ({doc['warm_start']:.4f})"
    return text


def penalty_per_size(criterion: Criterion, n: int, m: int, max_terms: int = 0) -> np.ndarray:
    """``pen(k)`` for k = 0..m, or a ValueError when the criterion is not certifiable.

    The criterion must be ``n ln(SSE/n) + pen(k)`` (checked numerically) with
    ``pen`` increasing. Sizes the criterion rules out (AICc with no degrees of
    freedom left) and sizes above ``max_terms`` (when > 0) get ``+inf``: no
    structure of those sizes can be selected, nor certified.
    """
    if criterion.name not in CERTIFIABLE or criterion.needs_coefficients:
        raise ValueError(
            f"criterion {criterion.name} cannot be certified: its value depends on more "
            f"than the SSE and the number of terms (certifiable: {', '.join(CERTIFIABLE)})")
    k = np.arange(m + 1)
    with np.errstate(invalid="ignore"):
        pen = criterion(np.full(m + 1, float(n)), n, k, None)
        check = criterion(np.full(m + 1, float(n) * np.e), n, k, None)
    finite = np.isfinite(pen)
    usable = int(finite.sum())  # only the largest sizes may be ruled out
    head = slice(0, usable)
    if (usable == 0 or not finite[head].all() or not np.allclose(check[head] - pen[head], n)
            or np.any(np.diff(pen[head]) <= 0)):
        raise ValueError(f"criterion {criterion.name} is not of the form N ln(SSE/N) + pen(k)")
    if max_terms and max_terms < m:
        pen = pen.copy()
        pen[max_terms + 1:] = np.inf
    return pen


def mse_bounds(value: float, lower: float, mask: np.ndarray, pen: np.ndarray,
                n: float) -> dict:
    """The best structure's one-step MSE, and the least of any structure of its size or less.

    ``value = N ln(MSE) + pen(k)`` read backwards at k = its size.
    """
    k = int(np.count_nonzero(mask))
    if not (k and np.isfinite(value) and np.isfinite(pen[k])):
        return {}
    mse = float(np.exp((value - pen[k]) / n))
    low = float(np.exp((lower - pen[k]) / n)) if np.isfinite(lower) else 0.0
    return {"one_step_mse": mse, "mse_lower_bound": min(low, mse)}


def trivial_bound(r_aug: np.ndarray, n: float, scale: float, floor: float,
                   pen: np.ndarray) -> float:
    """No structure scores below the SSE of all terms with the penalty of one term."""
    mu = r_aug.shape[1] - 1
    sse = float(r_aug[mu, mu] ** 2) if r_aug.shape[0] > mu else 0.0
    return float(n * np.log(max(sse, floor) * scale / n) + pen[1]) if mu else np.inf

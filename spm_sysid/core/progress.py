"""Where a job is: one progress record for progress bars, logs and ROS feedback.

A job goes through phases (:data:`PHASES`): checking the data, choosing the
orders from the data (``orders: auto``), the GA search, its polish (the local
search after it), the certification (branch and bound), the simulation focus's
screening of structures and its judgement of finalists on held-out blocks, the
refinement of the chosen model, and the validation. Each reports
:class:`Progress` records to a callback; the command line draws them as
progress bars, the node logs them and sends them as an action's feedback.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["PHASES", "Progress", "ProgressFn"]

#: The phases of a job, in order.
PHASES = ("checking data", "orders", "search", "polish", "certification", "screening",
          "held-out blocks", "refinement", "validation")


@dataclass(frozen=True)
class Progress:
    """One progress report.

    Attributes
    ----------
    phase : str
        One of :data:`PHASES`.
    step : int
        Generation (search), work done (polish: neighbourhoods ranked or
        structures scored), nodes explored (certification), structures refined
        (refinement).
    total : int
        Steps in the phase when known (generations, structures to refine); 0
        when not known.
    best : float
        Best criterion value so far (NaN when none yet).
    evaluations : int
        Structures fitted so far.
    bound : float
        The certification's lower bound (NaN outside certification).
    elapsed : float
        Seconds since the job began.
    best_model : callable, optional
        Builds the best model so far (the search's best by the criterion, fitted
        by least squares; at validation, the chosen one), for a job stopped
        before its end (Ctrl-C): called only then, so reports stay cheap.
    """

    phase: str
    step: int = 0
    total: int = 0
    best: float = math.nan
    evaluations: int = 0
    bound: float = math.nan
    elapsed: float = 0.0
    best_model: Callable[[], object] | None = field(default=None, compare=False, repr=False)

    def __getstate__(self) -> dict:
        """Pickle without ``best_model``: a builder is local to its process.

        The node's worker sends these records to the node through a pipe; the
        builder (a closure over the job's state) stays behind.
        """
        return {k: v for k, v in self.__dict__.items() if k != "best_model"}

    def __setstate__(self, state: dict) -> None:
        for k, v in {**state, "best_model": None}.items():
            object.__setattr__(self, k, v)  # frozen: set as __init__ does

    @property
    def gap(self) -> float:
        """``best - bound`` during certification (NaN otherwise)."""
        return self.best - self.bound if math.isfinite(self.bound) else math.nan

    def line(self) -> str:
        """One line for a log or a terminal: only the figures that mean something now.

        ``search: generation 120/300, best -10744.78, 21805 structures fitted,
        0.3 s``; ``validation, 0.5 s`` (no "0, 0 structures" for a phase
        without steps).
        """
        parts = []
        if self.total or self.step:
            name = {"search": "generation ", "certification": "node "}.get(self.phase, "step ")
            parts.append(f"{name}{self.step}" + (f"/{self.total}" if self.total else ""))
        if math.isfinite(self.best):
            parts.append(f"best {self.best:.2f}")
        if math.isfinite(self.bound):
            parts.append(f"lower bound {self.bound:.2f} (gap {self.gap:.2f})")
        if self.evaluations:
            parts.append(f"{self.evaluations} structures fitted")
        parts.append(f"{self.elapsed:.1f} s")
        return f"{self.phase}{': ' if len(parts) > 1 else ', '}" + ", ".join(parts)


#: What a progress callback looks like.
ProgressFn = Callable[[Progress], None]

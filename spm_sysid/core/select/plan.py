"""How a structure will be chosen, decided once: the selection plan.

The focus (what the model is for), the selection (criterion or held-out
blocks), whether the record's free run means anything (the open-loop check),
and the held-out folds are decided here, together, before any structure is
judged. Every later step reads the :class:`SelectionPlan`; none branches on the
settings again.

* ``mode``: ``criterion`` (the paper's: the criterion on the estimation data)
  or ``validated`` (the error on held-out blocks); ``auto`` validates the
  simulation focus, and the prediction focus with fewer than
  :data:`~spm_sysid.core.defaults.ROWS_PER_TERM` rows per usable candidate; a
  record that cannot be folded is judged by the criterion, and says why.
* ``judged``: ``one-step`` (focus prediction), ``free-run`` (focus simulation),
  or ``k-step`` (focus simulation on a record that integrates or is unstable in
  open loop: its free run drifts whatever the model, so free-run errors do not
  compare models).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..defaults import FOLDS, HORIZON, OPEN_LOOP_ORDER, ROWS_PER_TERM, SIMULATION_REPEATS
from ..options import SearchOptions
from ..validate.open_loop import OpenLoop, open_loop_check
from .folds import Fold, informative_folds, is_long

__all__ = ["SelectionPlan", "plan_selection"]


@dataclass(frozen=True)
class SelectionPlan:
    """What is judged, how, and on which folds (see the module doc).

    Attributes
    ----------
    mode : str
        ``criterion`` or ``validated``.
    judged : str
        ``one-step``, ``free-run`` or ``k-step``.
    horizon : int or None
        The k of ``k-step`` (None otherwise).
    folds : list of Fold
        The held-out folds (empty when the record cannot be folded).
    note : str
        Why this mode (the document's ``selection.note``).
    open_loop : OpenLoop or None
        The open-loop check (focus simulation).
    warnings : list of str
        What the answer must say about the plan.
    """

    mode: str
    judged: str
    horizon: int | None
    folds: list[Fold]
    note: str
    open_loop: OpenLoop | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def simulate(self) -> bool:
        """Structures are judged on their free run."""
        return self.judged == "free-run"

    @property
    def by_criterion_on_prediction(self) -> bool:
        """The paper's path: the criterion's best, least squares (certifiable)."""
        return self.mode == "criterion" and self.judged == "one-step"


def _mode(selection: str, focus: str, problem) -> tuple[str, str]:
    """``criterion`` or ``validated``, and why."""
    if selection != "auto":
        return selection, "as asked"
    if focus == "simulation":
        return "validated", "auto: the simulation focus is always validated"
    per_term = problem.rows / max(int(problem.usable.sum()), 1)
    if per_term < ROWS_PER_TERM:
        return "validated", (f"auto: {per_term:.1f} rows per candidate term (fewer than "
                             f"{ROWS_PER_TERM}): an in-sample criterion could overfit")
    return "criterion", f"auto: {per_term:.1f} rows per candidate term"


def plan_selection(problem, options: SearchOptions) -> SelectionPlan:
    """The plan for ``problem`` with these options (see the module doc)."""
    mode, note = _mode(options.selection, options.focus, problem)
    warnings: list[str] = []
    open_loop, judged, horizon = None, "one-step", None
    if options.focus == "simulation":
        open_loop = open_loop_check(problem.u, problem.y, problem.segments,
                                    min(max(problem.term_space.ny, OPEN_LOOP_ORDER), 10))
        judged = "free-run"
        if open_loop is not None and not open_loop.free_run_applies:
            judged, horizon = "k-step", options.horizon or HORIZON
            warnings.append(open_loop.reason().replace(
                "judged on the k-step prediction", f"judged on the {horizon}-step prediction"))
    if options.focus == "simulation":
        repeats = options.simulation_repeats
        if repeats is None:
            repeats = 1 if is_long(problem) else SIMULATION_REPEATS
        folds, fold_note = informative_folds(problem, options.simulation_folds, repeats)
    else:
        folds, fold_note = informative_folds(problem, FOLDS)
    if mode == "validated" and not folds:
        mode, note = "criterion", fold_note
        if options.selection != "criterion" and "excitation" in fold_note:
            warnings.append(f"judged by the criterion on all the data, not on held-out "
                            f"blocks: {fold_note}")
    elif fold_note:
        note = f"{note}; {fold_note}"
    if open_loop is not None and open_loop.note():
        warnings.append(open_loop.note())
    return SelectionPlan(mode, judged, horizon, folds, note, open_loop, warnings)

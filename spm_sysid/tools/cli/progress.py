"""Progress bars on the terminal: one helper for every command.

:class:`PhaseBars` draws a job's :class:`~spm_sysid.core.progress.Progress`
records (a bar per phase: generations of the search, nodes of the
certification, structures refined); :func:`count_bar` counts finished items
(runs of a study, inputs of a batch). Bars go to stderr and stay silent when
stderr is not a terminal (tqdm's ``disable=None``) or with ``--quiet``.
"""

from __future__ import annotations

import math
import sys

from ...core.progress import Progress

__all__ = ["PhaseBars", "count_bar"]

_UNITS = {"search": "gen", "certification": " nodes", "refinement": " structures"}


def _bar(**kw):
    from tqdm import tqdm

    return tqdm(file=sys.stderr, leave=False, disable=None, **kw)


class PhaseBars:
    """Draws Progress records: a bar for the current phase, replaced when it changes."""

    def __init__(self, enabled: bool = True) -> None:
        # tqdm stays silent off a terminal; not importing it then saves its import time
        self.enabled = enabled and _terminal()
        self.phase: str | None = None
        self.bar = None

    def __call__(self, p: Progress) -> None:
        if not self.enabled or p.phase not in _UNITS:
            return
        if p.phase != self.phase:
            self.close()
            self.phase = p.phase
            self.bar = _bar(total=p.total or None, desc=p.phase, unit=_UNITS[p.phase])
        self.bar.n = p.step
        post = {}
        if math.isfinite(p.best):
            post["best"] = f"{p.best:.2f}"
        if math.isfinite(p.bound):
            post["bound"] = f"{p.bound:.2f}"
        if p.evaluations:
            post["fits"] = p.evaluations
        self.bar.set_postfix(post, refresh=True)

    def generation(self, stats) -> None:
        """A GA generation (:class:`~spm_sysid.core.search.ga.GenerationStats`) as progress."""
        self(Progress("search", stats.generation, self._total, stats.best, stats.evaluations))

    def for_generations(self, total: int) -> PhaseBars:
        """Set the number of generations for :meth:`generation`; returns self."""
        self._total = total
        return self

    _total = 0

    def nodes(self, nodes: int, best: float, lower: float) -> None:
        """A branch-and-bound report as progress."""
        self(Progress("certification", nodes, 0, best, bound=lower))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def count_bar(total: int, desc: str, unit: str, enabled: bool = True):
    """A bar counting finished items (None when disabled or stderr is not a terminal)."""
    return _bar(total=total, desc=desc, unit=unit) if enabled and _terminal() else None


def _terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False

"""Progress on the terminal and off it: one helper for every command.

:class:`PhaseBars` shows a job's :class:`~spm_sysid.core.progress.Progress`
records (the search's generations, the certification's nodes, the structures
refined, the held-out blocks judged ...):

* on a terminal, a live bar per phase (tqdm), replaced when the phase changes;
* off a terminal (a log, CI, ``| tee``), a line on stderr at each new phase and
  then at least every :data:`LINE_EVERY` seconds -- the phase, how far it is
  (``step/total`` and the share done, when the total is known), the seconds
  elapsed, and an estimate of the phase's remaining seconds from its pace
  after its first step (a phase's first step is often its dearest: a cold
  cache, a compiled kernel, the longest fold; its pace alone said 146 s where
  30 s followed on a 10-minute record), none until a second step is done. A
  phase whose steps are long (one refinement on 10^5 samples) still gets its
  line: a clock prints the last record again, with the time, when nothing new
  came for that long.

:func:`count_bar` counts finished items (runs of a study, inputs of a batch).
``--quiet`` silences both.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import replace

from ...core.progress import Progress

__all__ = ["LINE_EVERY", "PhaseBars", "count_bar"]

_UNITS = {"search": "gen", "polish": " steps", "certification": " nodes",
          "refinement": " structures",
          "orders": " orders", "screening": " structures", "held-out blocks": " finalists"}

#: Seconds between progress lines off a terminal (at most).
LINE_EVERY = 10.0


def _bar(**kw):
    from tqdm import tqdm

    return tqdm(file=sys.stderr, leave=False, disable=None, **kw)


class PhaseBars:
    """Shows Progress records: a bar on a terminal, lines off it (see the module doc)."""

    def __init__(self, enabled: bool = True, stream=None, every: float = LINE_EVERY,
                 clock=time.monotonic) -> None:
        self.stream = stream or sys.stderr
        self.clock = clock  # seconds, monotonic (a test gives its own)
        # tqdm stays silent off a terminal; not importing it then saves its import time
        self.enabled = enabled and _terminal(self.stream)
        self.logging = enabled and not self.enabled
        self.every = every
        self.phase: str | None = None
        self.bar = None
        self._last: Progress | None = None
        self.best_model = None  # builds the job's best model so far (Progress.best_model)
        self.best_phase = self.last_phase = ""
        self._fresh = False  # a record came since the last line
        self._printed = self._t0 = clock()
        self._pace_from: tuple[float, int] | None = None  # (time, step) after the first step
        self._seen_at = self._t0  # when the last record came
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._clock = None
        if self.logging:
            self._clock = threading.Thread(target=self._tick, daemon=True, name="progress")
            self._clock.start()

    def __call__(self, p: Progress) -> None:
        self.last_phase = p.phase
        if p.best_model is not None:
            self.best_model, self.best_phase = p.best_model, p.phase
        if self.logging:
            self._log(p)
        if not self.enabled or p.phase not in _UNITS:
            return
        if p.phase != self.phase:
            self.close_bar()
            self.phase = p.phase
            self.bar = _bar(total=p.total or None, desc=p.phase, unit=_UNITS[p.phase])
        if p.total and p.total != self.bar.total:  # a phase may learn it has more to do
            self.bar.total = p.total
        self.bar.n = p.step
        post = {}
        if math.isfinite(p.best):
            post["best"] = f"{p.best:.2f}"
        if math.isfinite(p.bound):
            post["bound"] = f"{p.bound:.2f}"
        if p.evaluations:
            post["fits"] = p.evaluations
        self.bar.set_postfix(post, refresh=True)

    # -- lines off a terminal -------------------------------------------------------------
    def _log(self, p: Progress) -> None:
        with self._lock:
            now = self.clock()
            new_phase = p.phase != (self._last.phase if self._last else None)
            if new_phase or (self._pace_from and p.step < self._pace_from[1]):  # began anew
                self._pace_from = None
            if self._pace_from is None and p.step >= 1:
                self._pace_from = (now, p.step)
            self._last, self._fresh, self._seen_at = p, True, now
            if new_phase or now - self._printed >= self.every:
                self._print(p, now)

    def _print(self, p: Progress, now: float, still: bool = False) -> None:
        text = p.line() + (" (still working on this step)" if still else "")
        if p.total and p.step:
            text += f"; {min(p.step / p.total, 1.0):.0%} of this phase"
            left = self._left(p, now)
            if left is not None:
                text += f", about {left:.0f} s left in it"
        print(text, file=self.stream, flush=True)
        self._printed, self._fresh = now, False

    def _left(self, p: Progress, now: float) -> float | None:
        """Seconds left in the phase at the pace of its steps after the first (None: no pace)."""
        if self._pace_from is None or p.step >= p.total:
            return None
        since, first = self._pace_from
        if p.step <= first or self._seen_at - since < 1.0:
            return None
        left = (self._seen_at - since) / (p.step - first) * (p.total - p.step)
        left -= now - self._seen_at  # a step under way has spent part of it
        return left if left >= 1.0 else None

    def _tick(self) -> None:
        """Every so often: the last record again when nothing new came (a long step)."""
        while not self._stop.wait(min(1.0, self.every / 2)):
            with self._lock:
                now = self.clock()
                if self._last is not None and now - self._printed >= self.every:
                    last = replace(self._last, elapsed=now - self._t0)
                    self._print(last, now, still=not self._fresh)

    # -- search reports -------------------------------------------------------------------
    def generation(self, stats) -> None:
        """A GA generation (:class:`~spm_sysid.core.search.ga.GenerationStats`) as progress."""
        self(Progress("search", stats.generation, self._total, stats.best, stats.evaluations,
                      elapsed=self.clock() - self._t0))

    def for_generations(self, total: int) -> PhaseBars:
        """Set the number of generations for :meth:`generation`; returns self."""
        self._total = total
        return self

    _total = 0

    def nodes(self, nodes: int, best: float, lower: float) -> None:
        """A branch-and-bound report as progress."""
        self(Progress("certification", nodes, 0, best, bound=lower,
                      elapsed=self.clock() - self._t0))

    def close_bar(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def close(self) -> None:
        """The bar closed; no more lines (the clock stops)."""
        self.close_bar()
        self._stop.set()


def count_bar(total: int, desc: str, unit: str, enabled: bool = True):
    """A bar counting finished items (None when disabled or stderr is not a terminal)."""
    return _bar(total=total, desc=desc, unit=unit) if enabled and _terminal(sys.stderr) \
        else None


def _terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False

"""A bounded, time-aligned buffer of (input, output) sample pairs.

Input and output samples arrive separately (two topics); the buffer pairs them
by stamp, keeps at most ``capacity`` pairs (the oldest are dropped first) and
counts everything it does not keep, so nothing is lost silently:

``rejected_nonfinite``     NaN or inf values
``rejected_out_of_order``  a stamp not later than the previous one of its stream
                           (a lone sample stamped in the past)
``time_jumps``             times a stream's stamps went back for good (see below)
``discarded_on_jump``      waiting samples stamped after the jump, dropped with it
``unpaired_inputs/outputs``  samples that can no longer find a partner
``dropped_oldest``         pairs pushed out by a full buffer

Stamps that go back (a replayed bag, a restarted driver, or one sample stamped
far in the future before them) are held, not dropped at once: when
``resync_samples`` consecutive held samples of a stream are in order among
themselves, the stream's clock is taken to have jumped back: the held samples
are accepted as the start of a new timeline, and any waiting samples of that
stream stamped after them are discarded (counted). A lone late sample followed
by in-order ones is rejected (counted). So a single far-future stamp costs
itself and never blocks a stream, and a bag replayed into a running node
becomes a new segment after ``resync_samples`` samples. Pair stamps that go
back mark a new segment (see :mod:`spm_sysid.core.narx.segments`).

Pairing: each stream is in stamp order, so a sample pairs with the oldest
waiting sample of the other stream when their stamps differ by at most
``tolerance_ns``; waiting samples that are older than that by more than the
tolerance can never pair and are counted as unpaired. At most ``max_pending``
samples wait per stream (a silent partner stream must not grow memory).

Independent of ROS and thread-safe: the node's subscription callbacks add
samples while an identification works on a :meth:`snapshot`.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["BufferStats", "SampleBuffer", "pair_streams"]


@dataclass
class BufferStats:
    """Counters of a :class:`SampleBuffer` (cumulative since creation)."""

    samples: int = 0
    capacity: int = 0
    received_inputs: int = 0
    received_outputs: int = 0
    paired: int = 0
    dropped_oldest: int = 0
    rejected_nonfinite: int = 0
    rejected_out_of_order: int = 0
    time_jumps: int = 0
    discarded_on_jump: int = 0
    held_out_of_order: int = 0
    unpaired_inputs: int = 0
    unpaired_outputs: int = 0
    pending_inputs: int = 0
    pending_outputs: int = 0
    cleared: int = 0

    def to_dict(self) -> dict[str, int]:
        """Plain dictionary (for diagnostics and JSON)."""
        return asdict(self)


class SampleBuffer:
    """Pairs input/output samples by stamp into a bounded ring buffer.

    Parameters
    ----------
    capacity : int
        Most pairs kept; when full the oldest pair is dropped (and counted).
    tolerance_ns : int
        Largest stamp difference of a pair, nanoseconds.
    max_pending : int
        Most unpaired samples waiting per stream.
    resync_samples : int
        Consecutive in-order samples behind a stream's last stamp that make the
        buffer accept a jump back in time (see the module docstring).
    """

    def __init__(self, capacity: int, tolerance_ns: int = 0, max_pending: int = 10_000,
                 resync_samples: int = 10) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance_ns}")
        self.capacity = int(capacity)
        self.tolerance_ns = int(tolerance_ns)
        self.max_pending = int(max_pending)
        if resync_samples < 1:
            raise ValueError(f"resync_samples must be >= 1, got {resync_samples}")
        self.resync_samples = int(resync_samples)
        self._held: dict[str, list[tuple[int, float]]] = {"u": [], "y": []}
        self.jumps: list[tuple[str, int, int]] = []  # (stream, from stamp, to stamp)
        self._lock = threading.Lock()
        self._stamps = np.zeros(self.capacity, dtype=np.int64)
        self._u = np.zeros(self.capacity)
        self._y = np.zeros(self.capacity)
        self._start = 0
        self._size = 0
        self._pending = {"u": deque(), "y": deque()}
        self._last = {"u": None, "y": None}
        self.stats = BufferStats(capacity=self.capacity)

    def __len__(self) -> int:
        return self._size

    # -- input ----------------------------------------------------------------------
    def add_input(self, stamp_ns: int, value: float) -> bool:
        """Add an input sample; True when it was accepted (paired or waiting).

        False when it was rejected or is held as out of order (see the module
        docstring: held samples are accepted later if their stream jumped back).
        """
        return self._add("u", int(stamp_ns), value)

    def add_output(self, stamp_ns: int, value: float) -> bool:
        """Add an output sample; True when it was accepted (paired or waiting)."""
        return self._add("y", int(stamp_ns), value)

    def _add(self, stream: str, stamp: int, value: float) -> bool:
        with self._lock:
            st = self.stats
            if stream == "u":
                st.received_inputs += 1
            else:
                st.received_outputs += 1
            if not math.isfinite(value):
                st.rejected_nonfinite += 1
                return False
            last = self._last[stream]
            if last is not None and stamp <= last:
                return self._hold(stream, stamp, float(value))
            if self._held[stream]:  # a run of late samples ended: they were outliers
                st.rejected_out_of_order += len(self._held[stream])
                self._held[stream].clear()
                self._update_pending()
            self._accept(stream, stamp, float(value))
            return True

    def _hold(self, stream: str, stamp: int, value: float) -> bool:
        """Keep a sample stamped before its stream's last one; resync after a run."""
        held = self._held[stream]
        if held and stamp <= held[-1][0]:  # not in order among the held: start over
            self.stats.rejected_out_of_order += len(held)
            held.clear()
        held.append((stamp, value))
        if len(held) < self.resync_samples:
            self._update_pending()
            return False  # not accepted (yet): held, see the module docstring
        # the stream's clock went back for good: a new timeline starts at held[0]
        first = held[0][0]
        self.stats.time_jumps += 1
        self.jumps.append((stream, int(self._last[stream]), int(first)))
        mine = self._pending[stream]
        stale = [item for item in mine if item[0] >= first]
        if stale:
            self.stats.discarded_on_jump += len(stale)
            self._pending[stream] = deque(item for item in mine if item[0] < first)
        self._last[stream] = None
        run, self._held[stream] = list(held), []
        for t, v in run:
            self._accept(stream, t, v)
        return True

    def _accept(self, stream: str, stamp: int, value: float) -> None:
        other = "y" if stream == "u" else "u"
        self._last[stream] = stamp
        waiting = self._pending[other]
        # partners older than stamp - tolerance can never pair any more
        while waiting and waiting[0][0] < stamp - self.tolerance_ns:
            waiting.popleft()
            self._count_unpaired(other, 1)
        if waiting and abs(waiting[0][0] - stamp) <= self.tolerance_ns:
            other_stamp, other_value = waiting.popleft()
            u, y = (value, other_value) if stream == "u" else (other_value, value)
            self._append(max(stamp, other_stamp), u, y)
        else:
            mine = self._pending[stream]
            mine.append((stamp, value))
            if len(mine) > self.max_pending:
                mine.popleft()
                self._count_unpaired(stream, 1)
        self._update_pending()

    def _count_unpaired(self, stream: str, n: int) -> None:
        if stream == "u":
            self.stats.unpaired_inputs += n
        else:
            self.stats.unpaired_outputs += n

    def _update_pending(self) -> None:
        self.stats.pending_inputs = len(self._pending["u"])
        self.stats.pending_outputs = len(self._pending["y"])
        self.stats.held_out_of_order = len(self._held["u"]) + len(self._held["y"])

    def _append(self, stamp: int, u: float, y: float) -> None:
        if self._size == self.capacity:
            self._start = (self._start + 1) % self.capacity
            self._size -= 1
            self.stats.dropped_oldest += 1
        i = (self._start + self._size) % self.capacity
        self._stamps[i], self._u[i], self._y[i] = stamp, u, y
        self._size += 1
        self.stats.paired += 1
        self.stats.samples = self._size

    # -- output ---------------------------------------------------------------------
    def snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of ``(stamps_ns, u, y)``, oldest first; recording goes on meanwhile."""
        with self._lock:
            idx = (self._start + np.arange(self._size)) % self.capacity
            return self._stamps[idx].copy(), self._u[idx].copy(), self._y[idx].copy()

    def stats_dict(self) -> dict[str, int]:
        """A consistent copy of the counters."""
        with self._lock:
            return self.stats.to_dict()

    def clear(self) -> int:
        """Empty the buffer and the waiting samples; returns the pairs removed."""
        with self._lock:
            removed = self._size
            self._start = self._size = 0
            self._pending["u"].clear()
            self._pending["y"].clear()
            self._held = {"u": [], "y": []}
            self._last = {"u": None, "y": None}
            self.stats.samples = 0
            self.stats.cleared += removed
            self._update_pending()
            return removed


def pair_streams(events, tolerance_ns: int, resync_samples: int = 10
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, BufferStats]:
    """Pair recorded samples offline exactly as the node pairs them live.

    Parameters
    ----------
    events : iterable of (stream, stamp_ns, value)
        ``stream`` is ``"u"`` or ``"y"``, in arrival (log) order.
    tolerance_ns, resync_samples : int
        As for :class:`SampleBuffer` (the node's ``stamp_tolerance`` and
        ``resync_samples``).

    Returns
    -------
    stamps_ns, u, y : ndarray
        The pairs, in order.
    stats : BufferStats
        What was rejected, left unpaired, or held.
    """
    events = list(events)
    buf = SampleBuffer(max(1, len(events)), tolerance_ns, max_pending=max(1, len(events)),
                       resync_samples=resync_samples)
    for stream, stamp, value in events:
        (buf.add_input if stream == "u" else buf.add_output)(stamp, value)
    stamps, u, y = buf.snapshot()
    return stamps, u, y, buf.stats


"""A bounded, time-aligned buffer of (inputs, outputs) samples.

Input and output samples arrive separately (one or several output topics and
one or several input topics, each carrying one or several signals: two joint
velocities of one ``JointState``); the buffer aligns them by
stamp, keeps at most ``capacity`` aligned samples ("pairs"; the oldest are
dropped first) and counts everything it does not keep, so nothing is lost
silently:

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
back mark a new segment (see :mod:`spm_sysid.core.model.segments`).

Alignment: each stream is in stamp order, so the oldest waiting samples of all
streams form one aligned sample when their stamps lie within ``tolerance_ns``
(its stamp is the latest of them). A waiting sample older than a newly arrived
sample of another stream by more than the tolerance, with no partner waiting in
that stream, can never align and is counted as unpaired. At most
``max_pending`` samples wait per stream (a silent partner stream must not grow
memory). Counters of inputs sum over the input streams.

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
    """Aligns input and output samples by stamp into a bounded ring buffer.

    Parameters
    ----------
    capacity : int
        Most aligned samples kept; when full the oldest is dropped (and counted).
    tolerance_ns : int
        Largest stamp difference within one aligned sample, nanoseconds.
    max_pending : int
        Most unaligned samples waiting per stream.
    resync_samples : int
        Consecutive in-order samples behind a stream's last stamp that make the
        buffer accept a jump back in time (see the module docstring).
    input_widths : sequence of int
        One entry per input stream (topic): how many input values each of its
        samples carries (e.g. two joint efforts of one ``JointState``). The
        default, ``(1,)``, is one input; the inputs are numbered stream by stream.
    output_widths : sequence of int
        The same for the output streams (default one output); several outputs
        make ``y`` of :meth:`snapshot` one column per output.
    """

    def __init__(self, capacity: int, tolerance_ns: int = 0, max_pending: int = 10_000,
                 resync_samples: int = 10, input_widths=(1,), output_widths=(1,)) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance_ns}")
        if resync_samples < 1:
            raise ValueError(f"resync_samples must be >= 1, got {resync_samples}")
        widths = [int(w) for w in input_widths]
        if not widths or min(widths) < 1:
            raise ValueError(f"input_widths must be one or more positive counts, got {widths}")
        out_widths = [int(w) for w in output_widths]
        if not out_widths or min(out_widths) < 1:
            raise ValueError(f"output_widths must be one or more positive counts, got "
                             f"{out_widths}")
        self.capacity = int(capacity)
        self.tolerance_ns = int(tolerance_ns)
        self.max_pending = int(max_pending)
        self.resync_samples = int(resync_samples)
        # streams 0..k-1 are the output topics, streams k.. the input topics
        self._n_out = len(out_widths)
        self.names = ((["y"] if self._n_out == 1 else [f"y{i + 1}" for i in range(self._n_out)])
                      + (["u"] if len(widths) == 1 else
                         [f"u{i + 1}" for i in range(len(widths))]))
        self._widths = out_widths + widths
        self.n_inputs = sum(widths)
        self.n_outputs = sum(out_widths)
        self._slices = []
        at = 0
        for w in widths:
            self._slices.append(slice(at, at + w))
            at += w
        n = len(self._widths)
        self._held: list[list[tuple[int, tuple]]] = [[] for _ in range(n)]
        self.jumps: list[tuple[str, int, int]] = []  # (stream, from stamp, to stamp)
        self._lock = threading.Lock()
        self._stamps = np.zeros(self.capacity, dtype=np.int64)
        self._u = np.zeros((self.capacity, self.n_inputs))
        self._y = np.zeros((self.capacity, self.n_outputs))
        self._start = 0
        self._size = 0
        self._pending: list[deque] = [deque() for _ in range(n)]
        self._last: list[int | None] = [None] * n
        self.stats = BufferStats(capacity=self.capacity)
        #: called as ``on_pair(stamp_ns, u, y)`` for each new aligned sample (``u`` in
        #: stream order; ``y`` a number, or an array in stream order for several
        #: outputs), after the buffer's lock is released (online prediction)
        self.on_pair = None
        self._paired: list[tuple] = []

    def __len__(self) -> int:
        return self._size

    # -- input ----------------------------------------------------------------------
    def add_input(self, stamp_ns: int, value, stream: int = 0) -> bool:
        """Add a sample of input stream ``stream`` (a number, or one per input of it).

        True when it was accepted (aligned or waiting); False when it was rejected
        or is held as out of order (see the module docstring: held samples are
        accepted later if their stream jumped back).
        """
        return self._add(self._n_out + int(stream), int(stamp_ns), value)

    def add_output(self, stamp_ns: int, value, stream: int = 0) -> bool:
        """Add a sample of output stream ``stream``; True when it was accepted."""
        return self._add(int(stream), int(stamp_ns), value)

    def _add(self, stream: int, stamp: int, value) -> bool:
        accepted = self._add_locked(stream, stamp, value)
        if self._paired:  # outside the lock: the callback may take its time
            pairs, self._paired = self._paired, []
            for pair in pairs:
                self.on_pair(*pair)
        return accepted

    def _add_locked(self, stream: int, stamp: int, value) -> bool:
        values = ((float(value),) if isinstance(value, (int, float))
                  else tuple(float(v) for v in np.ravel(value)))
        if len(values) != self._widths[stream]:
            raise ValueError(f"stream {self.names[stream]} carries {self._widths[stream]} "
                             f"value(s) per sample, got {len(values)}")
        with self._lock:
            st = self.stats
            if stream >= self._n_out:
                st.received_inputs += 1
            else:
                st.received_outputs += 1
            if not all(math.isfinite(v) for v in values):
                st.rejected_nonfinite += 1
                return False
            last = self._last[stream]
            if last is not None and stamp <= last:
                return self._hold(stream, stamp, values)
            if self._held[stream]:  # a run of late samples ended: they were outliers
                st.rejected_out_of_order += len(self._held[stream])
                self._held[stream].clear()
                self._update_pending()
            self._accept(stream, stamp, values)
            return True

    def _hold(self, stream: int, stamp: int, values: tuple) -> bool:
        """Keep a sample stamped before its stream's last one; resync after a run."""
        held = self._held[stream]
        if held and stamp <= held[-1][0]:  # not in order among the held: start over
            self.stats.rejected_out_of_order += len(held)
            held.clear()
        held.append((stamp, values))
        if len(held) < self.resync_samples:
            self._update_pending()
            return False  # not accepted (yet): held, see the module docstring
        # the stream's clock went back for good: a new timeline starts at held[0]
        first = held[0][0]
        self.stats.time_jumps += 1
        self.jumps.append((self.names[stream], int(self._last[stream]), int(first)))
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

    def _accept(self, stream: int, stamp: int, values: tuple) -> None:
        """Queue a sample, drop what can no longer align, emit what aligns."""
        tol = self.tolerance_ns
        self._last[stream] = stamp
        mine = self._pending[stream]
        mine.append((stamp, values))
        if len(mine) > self.max_pending:
            mine.popleft()
            self._count_unpaired(stream, 1)
        # A waiting sample of another stream older than stamp - tol can no longer get a
        # partner from this stream (its stamps only grow) unless one is waiting here.
        for other, waiting in enumerate(self._pending):
            if other == stream:
                continue
            while waiting and waiting[0][0] < stamp - tol and not any(
                    abs(t - waiting[0][0]) <= tol for t, _ in mine):
                waiting.popleft()
                self._count_unpaired(other, 1)
        # Emit while the oldest waiting sample of every stream align within tol.
        queues = self._pending
        while all(queues):
            heads = [q[0][0] for q in queues]
            if max(heads) - min(heads) > tol:
                break
            items = [q.popleft() for q in queues]
            k = self._n_out
            self._append(max(heads), [v for _, vals in items[k:] for v in vals],
                         [v for _, vals in items[:k] for v in vals])
        self._update_pending()

    def _count_unpaired(self, stream: int, n: int) -> None:
        if stream >= self._n_out:
            self.stats.unpaired_inputs += n
        else:
            self.stats.unpaired_outputs += n

    def _update_pending(self) -> None:
        k = self._n_out
        self.stats.pending_inputs = sum(len(q) for q in self._pending[k:])
        self.stats.pending_outputs = sum(len(q) for q in self._pending[:k])
        self.stats.held_out_of_order = sum(len(h) for h in self._held)

    def _append(self, stamp: int, u, y) -> None:
        if self._size == self.capacity:
            self._start = (self._start + 1) % self.capacity
            self._size -= 1
            self.stats.dropped_oldest += 1
        i = (self._start + self._size) % self.capacity
        self._stamps[i], self._u[i], self._y[i] = stamp, u, y
        if self.on_pair is not None:
            self._paired.append((int(stamp), self._u[i].copy(), float(self._y[i, 0])
                                 if self.n_outputs == 1 else self._y[i].copy()))
        self._size += 1
        self.stats.paired += 1
        self.stats.samples = self._size

    # -- output ---------------------------------------------------------------------
    def snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of ``(stamps_ns, u, y)``, oldest first; recording goes on meanwhile.

        ``u`` has shape (n,) for one input and (n, n_inputs) for several; ``y``
        likewise (n,) or (n, n_outputs).
        """
        with self._lock:
            idx = (self._start + np.arange(self._size)) % self.capacity
            u, y = self._u[idx].copy(), self._y[idx].copy()
            return (self._stamps[idx].copy(), u[:, 0] if self.n_inputs == 1 else u,
                    y[:, 0] if self.n_outputs == 1 else y)

    def stats_dict(self) -> dict[str, int]:
        """A consistent copy of the counters."""
        with self._lock:
            return self.stats.to_dict()

    def clear(self) -> int:
        """Empty the buffer and the waiting samples; returns the pairs removed."""
        with self._lock:
            removed = self._size
            self._start = self._size = 0
            for q in self._pending:
                q.clear()
            self._held = [[] for _ in self._widths]
            self._last = [None] * len(self._widths)
            self.stats.samples = 0
            self.stats.cleared += removed
            self._update_pending()
            return removed


def pair_streams(events, tolerance_ns: int, resync_samples: int = 10, input_widths=(1,),
                 output_widths=(1,)) -> tuple[np.ndarray, np.ndarray, np.ndarray, BufferStats]:
    """Align recorded samples offline exactly as the node aligns them live.

    Parameters
    ----------
    events : iterable of (stream, stamp_ns, value)
        ``stream`` is ``"y"`` for the (first) output stream, ``("y", k)`` for
        output stream k, ``"u"`` (the first input stream) or the index of an
        input stream; events in arrival (log) order.
    tolerance_ns, resync_samples : int
        As for :class:`SampleBuffer` (the node's ``stamp_tolerance`` and
        ``resync_samples``).
    input_widths, output_widths : sequence of int
        Values per sample of each input and output stream, as for
        :class:`SampleBuffer`.

    Returns
    -------
    stamps_ns, u, y : ndarray
        The aligned samples, in order (``u`` of shape (n, n_inputs) when several).
    stats : BufferStats
        What was rejected, left unpaired, or held.
    """
    events = list(events)
    buf = SampleBuffer(max(1, len(events)), tolerance_ns, max_pending=max(1, len(events)),
                       resync_samples=resync_samples, input_widths=input_widths,
                       output_widths=output_widths)
    for stream, stamp, value in events:
        if stream == "y":
            buf.add_output(stamp, value)
        elif isinstance(stream, tuple):
            buf.add_output(stamp, value, stream[1])
        else:
            buf.add_input(stamp, value, 0 if stream == "u" else int(stream))
    stamps, u, y = buf.snapshot()
    return stamps, u, y, buf.stats

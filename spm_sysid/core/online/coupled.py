"""Several outputs on a live stream: one :class:`OnlineSession` per output, one verdict.

A coupled model (:class:`~spm_sysid.core.model.mimo.MimoModel`) predicts each
output one step ahead from the measured past of every output and input, so
each output is monitored by its own session, fed with the inputs and the other
outputs as extra input signals (as it was identified). The verdict of the whole
model is the worst output's state (``VALID`` < ``DEGRADED`` < ``INVALID``), its
reason naming the output; each output's own state is kept for the messages.
A k-step prediction (``horizon`` > 1) of one output uses the other outputs'
measured values in between (it is the output's own k-step prediction, not the
coupled one).

A model identified on a decimated record (``metadata.decimation``) is fed the
stream decimated once, here, before the outputs' sessions: the other outputs
it reads as inputs are outputs (block starts), not block means. A gap inside a
block is seen by the sessions only when it spans more than a decimated step.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..model.decimation import BlockDecimator, decimate_blocks, decimation_factor
from ..model.mimo import MimoModel, augmented_inputs
from .monitor import MonitorState
from .session import OnlineSample, OnlineSession, held_out_mse

__all__ = ["CoupledSession", "coupled_held_out_mse"]

_RANK = {"VALID": 0, "DEGRADED": 1, "INVALID": 2}


class CoupledSession:
    """Online prediction and monitoring of every output of a coupled model.

    Parameters
    ----------
    model : MimoModel
    residuals : ndarray of shape (n, outputs), or None
        The identification's one-step residuals (each output's monitor reference).
    **options
        As for :class:`OnlineSession` (monitor_window, tracking, forgetting,
        sample_period, gap_factor, horizon).
    """

    def __init__(self, model: MimoModel, residuals: np.ndarray | None = None,
                 **options) -> None:
        self.model = model
        self.outputs = tuple(model.outputs)
        res = None if residuals is None else np.asarray(residuals, dtype=float)
        factor = _factor(model)
        self.decimator = BlockDecimator(factor) if factor > 1 else None
        self.sessions = [OnlineSession(m, None if res is None or res.ndim != 2
                                       else res[:, i], decimate=1, **options)
                         for i, m in enumerate(model.models)]
        self.horizon = self.sessions[0].horizon
        self.tracker = None  # tracking per output: each session's tracker
        self._state = "VALID"
        self.transitions: list[tuple[int, str, str]] = []
        self.raw_samples = 0  # samples fed before decimation (with a decimator)

    def feed(self, stamp_ns: int, u, y) -> tuple[list[OnlineSample | None], bool]:
        """One paired sample (``y`` one value per output).

        Returns each output's sample (None while its history is short) and
        whether the whole model's state changed.
        """
        y = np.asarray(y, dtype=float)
        u = np.atleast_1d(np.asarray(u, dtype=float))
        if self.decimator is not None:  # one sample per block, at its end
            self.raw_samples += 1
            block = self.decimator.push(stamp_ns, u, y)
            if block is None:
                return [None] * len(self.sessions), False
            stamp_ns, u, y = block
        samples = [s.feed(stamp_ns, augmented_inputs(u[None, :], y[None, :], i)[0], float(y[i]))
                   for i, s in enumerate(self.sessions)]
        state = self.state.state
        changed = state != self._state
        if changed:
            self.transitions.append((stamp_ns, self._state, state))
            self._state = state
        return samples, changed

    @property
    def output_states(self) -> list[MonitorState]:
        return [s.state for s in self.sessions]

    @property
    def state(self) -> MonitorState:
        """The worst output's state, its reason naming the output."""
        states = self.output_states
        i = max(range(len(states)), key=lambda k: _RANK[states[k].state])
        st = states[i]
        return replace(st, reason=f"output {self.outputs[i]}: {st.reason}") if st.reason else st

    def change_stamp(self) -> int | None:
        """The earliest stamp where a change was detected in any output (None: none)."""
        stamps = [s.change_stamp() for s in self.sessions]
        stamps = [s for s in stamps if s is not None]
        return min(stamps) if stamps else None

    @property
    def gaps(self) -> int:
        return self.sessions[0].gaps

    def stats(self) -> dict:
        """Counters for diagnostics (the first output's stream counts, every output's state)."""
        out = dict(self.sessions[0].stats())
        out["transitions"] = len(self.transitions)
        out["microseconds_per_sample"] = sum(s.stats()["microseconds_per_sample"]
                                             for s in self.sessions)
        for name, st in zip(self.outputs, self.output_states):
            out[f"state_{name}"] = st.state
        if self.decimator is not None:
            out.update(samples=self.raw_samples, decimate=self.decimator.factor,
                       decimation_dropped=self.decimator.dropped)
        return out


def coupled_held_out_mse(model: MimoModel, u: np.ndarray, Y: np.ndarray) -> float:
    """The outputs' one-step MSE on held-out samples, each over its variance, summed.

    Outputs of different units weigh alike; inf when any output cannot be predicted.
    """
    Y = np.asarray(Y, dtype=float)
    factor = _factor(model)
    if factor > 1:  # decimated once: the other outputs stay outputs
        u, Y, _, _ = decimate_blocks(np.asarray(u, dtype=float), Y, [(0, len(Y))], factor)
    total = 0.0
    for i, m in enumerate(model.models):
        var = float(np.var(Y[:, i])) or 1.0
        total += held_out_mse(m, augmented_inputs(u, Y, i), Y[:, i], decimate=1) / var
    return total


def _factor(model: MimoModel) -> int:
    """The decimation of a coupled model: its document's, else its first output's."""
    return max(decimation_factor(model.metadata), decimation_factor(model.models[0].metadata))

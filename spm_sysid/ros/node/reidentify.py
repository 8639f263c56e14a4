"""Automatic re-identification: when the model becomes INVALID, or periodically.

The policy (``reidentify``: never, when_invalid, periodic) picks the samples
(since the detected change, or the recent ones), holds out the most recent
share, identifies on the rest in the worker, and replaces the current model
only when the new one predicts the held-out samples better (one-step MSE).
Every run is counted for ``/diagnostics``.
"""

from __future__ import annotations

import math
import time

import numpy as np
from rclpy.node import Node

from ...core.model.mimo import MimoModel
from ...core.online.coupled import coupled_held_out_mse
from ...core.online.session import held_out_mse
from .identification import Identification
from .online import OnlinePart
from .publishing import SaveFailedError
from .recording import Recorder

__all__ = ["Reidentification"]


class Reidentification:
    """The automatic identifications of ``node``; ``counts`` for diagnostics.

    ``publish(result, model_path)`` saves and publishes a better model
    (:class:`~spm_sysid.ros.node.publishing.SaveFailedError` when it cannot be
    saved); ``on_done()`` runs after each comparison.
    """

    def __init__(self, node: Node, values, recorder: Recorder, identification: Identification,
                 online: OnlinePart, publish, on_done=None) -> None:
        self.node, self.values, self.recorder = node, values, recorder
        self.identification, self.online, self.publish = identification, online, publish
        self.on_done = on_done or (lambda: None)
        self.counts = {"runs": 0, "replaced": 0, "kept": 0, "failed": 0, "last": ""}
        self._last = -math.inf  # monotonic time of the last automatic start

    def maybe_start(self) -> None:
        """Start an automatic identification when the policy says so (and it can run)."""
        v, current, ident = self.values(), self.online.current(), self.identification
        policy = v["reidentify"]
        if policy == "never" or current is None or not ident.can_start_automatic():
            return
        now = time.monotonic()
        if now - max(self._last, current.since if policy == "periodic"
                     else -math.inf) < v["reidentify_interval"]:
            return
        if policy == "when_invalid":
            if current.state != "INVALID":
                return
            since = current.change_stamp
            why = "the model became INVALID"
        else:
            since, why = None, "periodic"
        stamps, u, y = self.recorder.snapshot()
        keep = np.ones(len(y), bool) if since is None else stamps >= since
        if policy == "periodic":  # the recent samples: the last reidentify_samples * 4
            keep[:max(len(y) - 4 * v["reidentify_samples"], 0)] = False
        if int(keep.sum()) < v["reidentify_samples"]:
            return  # not enough new samples yet; checked again every second
        if not ident.reserve_automatic():
            return
        self._last = now
        self.node.executor.create_task(self._run, stamps[keep], u[keep], y[keep], why)

    async def _run(self, stamps, u, y, why: str) -> None:
        """An automatic identification, compared with the current model.

        The new model replaces the current one only when it predicts the held-out
        recent samples better (one-step MSE).
        """
        v, counts, log = self.values(), self.counts, self.node.get_logger()
        hold = max(int(round(len(y) * v["reidentify_holdout"])), 20)
        fit = slice(0, len(y) - hold)
        counts["runs"] += 1
        log.info(f"automatic identification {counts['runs']} ({why}) on "
                 f"{len(y) - hold} samples, {hold} held out")
        try:
            record = self.recorder.record_of(u[fit], y[fit], stamps[fit],
                                             f"buffer of {self.node.get_fully_qualified_name()}"
                                             f" (automatic: {why})")
            out = await self.identification.run(record=record, auto=True)
        except Exception:  # the record could not be made: the reservation ends here
            self.identification.release_automatic()
            raise
        now = self.online.current()
        current = None if now is None else now.model
        if out.result is None or current is None:
            counts["failed"] += 1
            counts["last"] = f"failed: {out.message}"
            log.warning(f"automatic identification failed: {out.message}")
            return
        score = coupled_held_out_mse if isinstance(current, MimoModel) else held_out_mse
        new_mse = score(out.result.model, u[-hold:], y[-hold:])
        old_mse = score(current, u[-hold:], y[-hold:])
        if new_mse < old_mse:
            try:
                self.publish(out.result, v["model_path"])
            except SaveFailedError as exc:
                counts["failed"] += 1
                counts["last"] = f"failed: {exc}"
                log.error(str(exc))
                return
            counts["replaced"] += 1
            counts["last"] = f"replaced: held-out one-step MSE {new_mse:.4g} < {old_mse:.4g}"
            log.warning(f"automatic identification replaced the model (held-out one-step MSE "
                        f"{new_mse:.4g} vs {old_mse:.4g}): {out.message}")
        else:
            counts["kept"] += 1
            counts["last"] = f"kept: held-out one-step MSE {new_mse:.4g} >= {old_mse:.4g}"
            log.info(f"automatic identification kept the current model (held-out one-step "
                     f"MSE {new_mse:.4g} vs {old_mse:.4g})")
        self.on_done()

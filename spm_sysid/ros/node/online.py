"""The current model on the live stream: prediction, validity and tracking topics.

Every paired sample the buffer makes goes to the current model's session
(:class:`~spm_sysid.core.online.session.OnlineSession`, or
:class:`~spm_sysid.core.online.coupled.CoupledSession` for several outputs):
its one-step (and k-step) prediction on ``~/prediction``, the monitor's state
on ``~/validity`` (each change logged), the tracked coefficients on
``~/tracked_model``; samples beyond the ranges the model was fitted on are
counted (:class:`~spm_sysid.core.validate.envelope.RangeWatch`, the first one
logged). A failure is counted, never fatal to recording.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from spm_sysid_interfaces.msg import NarxModel as NarxModelMsg
from spm_sysid_interfaces.msg import Prediction, Validity

from ...core.model.mimo import MimoModel
from ...core.online.coupled import CoupledSession
from ...core.online.session import OnlineSession
from ...core.validate.envelope import RangeWatch
from ..common import LATCHED
from ..typed import prediction_message, tracked_message, validity_message
from .recording import Recorder

__all__ = ["CurrentModel", "OnlinePart"]


@dataclass(frozen=True)
class CurrentModel:
    """What others may read of the current model: a snapshot, never the live session.

    Attributes
    ----------
    model : NarxModel or MimoModel
    state : str
        The monitor's state (``VALID``, ``DEGRADED``, ``INVALID``).
    change_stamp : int or None
        The stamp (ns) where the detected change began.
    since : float
        Monotonic time the model was set.
    """

    model: object
    state: str
    change_stamp: int | None
    since: float


class OnlinePart:
    """Prediction and validity of the current model for ``node``.

    Parameters
    ----------
    node : Node
    values : callable
        The node's held parameter values, read when a model starts
        (``monitor``, its window, tracking, horizon, ``prediction_every``).
    recorder : Recorder
        Its buffer's pairs are fed here; its channel order maps them.
    on_invalid : callable
        Called when the model becomes INVALID (the re-identification policy).
    """

    def __init__(self, node: Node, values, recorder: Recorder, on_invalid) -> None:
        self.node, self.values, self.recorder, self.on_invalid = node, values, recorder, on_invalid
        self.pred_pub = node.create_publisher(Prediction, "~/prediction", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100,
            reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
        self.validity_pub = node.create_publisher(Validity, "~/validity", LATCHED)
        self.tracked_pub = node.create_publisher(NarxModelMsg, "~/tracked_model", LATCHED)
        self.session: OnlineSession | CoupledSession | None = None
        self.doc: dict | None = None
        self.ranges = RangeWatch(None, (), ())
        self.errors = 0
        self.predictions = 0
        self.model_time = time.monotonic()
        self.last_stamp: int | None = None
        self.dashboard = None  # the live page's sample store, when the node serves one
        recorder.buffer.on_pair = self.on_pair
        node.create_timer(values()["tracking_period"], self.publish_tracked)

    def start(self, model, doc: dict, residuals=None) -> None:
        """A new current model: a fresh session (its monitor starts VALID)."""
        v = self.values()
        self.model_time, self.doc = time.monotonic(), doc
        names = ((model.inputs, model.outputs) if isinstance(model, MimoModel) else
                 (model.term_space.inputs, (model.term_space.output,)))
        self.ranges = RangeWatch((doc.get("metadata") or {}).get("ranges"), *names)
        if self.dashboard is not None:
            self.dashboard.new_model()
        if not v["monitor"]:
            self.session = None
            return
        options = dict(monitor_window=v["monitor_window"], tracking=v["tracking"],
                       forgetting=v["forgetting"], sample_period=v["sample_period"],
                       gap_factor=v["gap_factor"], horizon=v["prediction_horizon"])
        try:
            if isinstance(model, MimoModel):  # one session per output
                self.session = CoupledSession(MimoModel.from_dict(doc), residuals, **options)
            else:
                self.session = OnlineSession(type(model).from_dict(doc), residuals,
                                             input_std=None, **options)
        except (ValueError, TypeError) as exc:  # e.g. a restored model without uncertainty
            self.session = None
            self.node.get_logger().warning(f"the model cannot be monitored online ({exc})")
            return
        sessions = getattr(self.session, "sessions", [self.session])
        if any(s.reference_source == "none" for s in sessions):
            self.node.get_logger().warning(
                "the model document carries no residual statistics (metadata.monitor: it was "
                "written by an older version); the monitor takes its residuals as white and "
                "may doubt a good model: identify again to monitor it against its own")
        self.publish_validity()

    def current(self) -> CurrentModel | None:
        """The current model and its monitor's state (None without a monitored model)."""
        session = self.session
        if session is None:
            return None
        return CurrentModel(session.model, session.state.state, session.change_stamp(),
                            self.model_time)

    def on_pair(self, stamp: int, u: np.ndarray, y) -> None:
        """Each new aligned sample (the buffer calls this): predict, monitor, track."""
        self.last_stamp = stamp
        session = self.session
        if session is None:
            return
        u = u[self.recorder.order] if len(u) > 1 else u[0]
        try:
            self._watch_range(u, y)
            samples, changed, names = self._feed(session, stamp, u, y)
        except Exception as exc:  # noqa: BLE001 - counted and reported, recording goes on
            self.errors += 1
            if self.errors == 1:
                self.node.get_logger().error(f"online prediction failed ({exc}); counted in "
                                             "/diagnostics (online_errors)")
            return
        if all(s is None for s in samples):
            return
        if self.dashboard is not None:
            self.dashboard.feed(names, samples)
        self.predictions += 1
        if self.predictions % self.values()["prediction_every"] == 0:
            for name, sample in zip(names, samples):
                if sample is not None:
                    self.pred_pub.publish(prediction_message(sample, session.horizon,
                                                             output_name=name))
        if changed:
            self._validity_changed(session, stamp)

    def _watch_range(self, u, y) -> None:
        """Count a sample beyond the model's fitted ranges; log the first of each model."""
        y = np.asarray(y)[self.recorder.out_order] if np.ndim(y) else y
        first = self.ranges.update(u, y)
        if first is not None:
            self.node.get_logger().warning(first)

    def _feed(self, session, stamp: int, u, y) -> tuple[list, bool, tuple[str, ...]]:
        """The session's new samples (one per output), whether validity changed, the names."""
        if isinstance(session, CoupledSession):
            samples, changed = session.feed(stamp, u, np.asarray(y)[self.recorder.out_order])
            return samples, changed, session.outputs
        sample = session.feed(stamp, u, y)
        return [sample], sample is not None and sample.changed, (
            session.model.term_space.output,)

    def _validity_changed(self, session, stamp: int) -> None:
        """Log and publish the new validity; an INVALID model calls for re-identification."""
        st = session.state
        text = f"model validity: {st.state}" + (f" ({st.reason})" if st.reason else "")
        # one call site per severity: rclpy refuses a site whose severity changes
        if st.state == "VALID":
            self.node.get_logger().info(text)
        else:
            self.node.get_logger().warning(text)
        self.validity_pub.publish(validity_message(session, stamp))
        if st.state == "INVALID":
            self.on_invalid()

    def publish_validity(self) -> None:
        self.validity_pub.publish(validity_message(self.session, self.last_stamp))

    def publish_tracked(self) -> None:
        session = self.session
        if session is None or session.tracker is None or self.doc is None:
            return
        stamp = self.node.get_clock().now().to_msg()
        self.tracked_pub.publish(tracked_message(self.doc, session.tracker, stamp))

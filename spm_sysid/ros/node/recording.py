"""Messages in, samples out: the subscriptions that fill the node's sample buffer.

One-line callbacks (image_pipeline's camera calibrator style) read each
message's field paths and stamp and hand them to the
:class:`~spm_sysid.core.stream.buffer.SampleBuffer`, which pairs inputs and
outputs by stamp. Everything that goes wrong is counted for ``/diagnostics``
and logged once: fields that cannot be read, stamps never set, publishers of
another message type on our topics (found in the graph: DDS never delivers
them), nodes of our name, samples rejected out of order, stamps jumping back.
"""

from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ...core.errors import FieldPathError, TooFewSamplesError
from ...core.io.channels import stream_order, topic_streams
from ...core.io.fields import MissingNameError, UnsetStamps, default_field, extract, parse_path
from ...core.record import Record
from ...core.stream.buffer import SampleBuffer
from ..common import RELIABLE_KEEP_ALL, message_class

__all__ = ["Recorder", "UNNAMED_CHECKS"]

#: Graph checks (1 s apart) to wait for discovery to name a publisher of a wrong type.
UNNAMED_CHECKS = 10


def _signal(msgtype: str, fields: list[str]):
    try:
        return message_class(msgtype), [parse_path(f or default_field(msgtype)) for f in fields]
    except (FieldPathError, ValueError) as exc:
        raise ValueError(str(exc)) from None


def describe(channels) -> str:
    """The channels in words, for the start-up log line."""
    return ", ".join(f"{c.name} = {c.topic} {c.field or default_field(c.msgtype)} "
                     f"({c.msgtype})" for c in channels)


class Recorder:
    """The buffer and the subscriptions of ``node`` that fill it.

    Parameters
    ----------
    node : Node
    values : dict
        The node's held parameter values (buffer, stamps, QoS).
    channels, out_channels : list
        The input and output channels (:func:`spm_sysid.core.io.channels.parse_channels`).
    """

    def __init__(self, node: Node, values: dict, channels: list, out_channels: list) -> None:
        self.node = node
        self.channels, self.out_channels = channels, out_channels
        streams, out_streams = topic_streams(channels), topic_streams(out_channels)
        self.order = np.argsort(stream_order(channels))  # buffer -> given order
        self.out_order = np.argsort(stream_order(out_channels))
        self.buffer = SampleBuffer(values["buffer_capacity"],
                                   int(round(values["stamp_tolerance"] * 1e9)),
                                   resync_samples=values["resync_samples"],
                                   input_widths=[len(idx) for _, _, idx in streams],
                                   output_widths=[len(idx) for _, _, idx in out_streams])
        self.topics = {f"input {topic}": (topic, msgtype) for topic, msgtype, _ in streams}
        self.topics.update({f"output {topic}": (topic, msgtype)
                            for topic, msgtype, _ in out_streams})
        self.field_errors = 0
        self.field_error = ""  # why the last message's field could not be read
        self.unnamed = 0  # messages that do not name a joint asked for by name: skipped
        self.unset = UnsetStamps()
        self.namesakes = 0
        self.type_mismatch: dict[tuple[str, str], str] = {}
        self._unnamed_checks = 0
        self._logged = {"rejected_out_of_order": 0, "time_jumps": 0}
        qos = RELIABLE_KEEP_ALL if not values["best_effort"] else QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=values["qos_depth"],
            reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
        for stream, (topic, msgtype, idx) in enumerate(streams):
            cls, steps = _signal(msgtype, [channels[i].field for i in idx])
            node.create_subscription(cls, topic, self._input_callback(stream, steps), qos)
        for stream, (topic, msgtype, idx) in enumerate(out_streams):
            cls, steps = _signal(msgtype, [out_channels[i].field for i in idx])
            node.create_subscription(cls, topic, self._output_callback(stream, steps), qos)
        node.create_timer(1.0, self.check_graph)

    # -- the callbacks -------------------------------------------------------------------
    def _input_callback(self, stream: int, steps: list):
        def on_input(msg) -> None:
            self._record(msg, stream, steps, lambda t, v: self.buffer.add_input(t, v, stream))
        return on_input

    def _output_callback(self, stream: int, steps: list):
        def on_output(msg) -> None:
            self._record(msg, ("y", stream), steps,
                         lambda t, v: self.buffer.add_output(t, v, stream))
        return on_output

    def _record(self, msg, stream, steps, add) -> None:
        try:
            value = [extract(msg, step) for step in steps]
        except MissingNameError as exc:  # another publisher's message on the topic
            self.unnamed += 1
            if self.unnamed == 1:
                self.node.get_logger().info(f"{exc}: such messages are skipped and counted "
                                            "in /diagnostics (another publisher on the topic?)")
            return
        except FieldPathError as exc:
            self.field_errors += 1
            self.field_error = str(exc)
            if self.field_errors == 1:
                self.node.get_logger().error(str(exc))
            return
        before = self.unset.count
        stamp = self.unset.stamp(stream, msg)
        if self.unset.count == 1 and before == 0:
            self.node.get_logger().warning(
                f"{type(msg).__name__} messages arrive with header.stamp 0 again and again "
                "(the publisher does not fill it in?): their receive times are used "
                "instead; such messages are counted in /diagnostics")
        add(self.node.get_clock().now().nanoseconds if stamp is None else stamp, value)

    # -- what was recorded ---------------------------------------------------------------
    def snapshot(self):
        """The buffer's samples with inputs and outputs in the order the parameters give."""
        stamps, u, y = self.buffer.snapshot()
        if u.ndim == 2:
            u = u[:, self.order]
        if y.ndim == 2:
            y = y[:, self.out_order]
        return stamps, u, y

    def record_of(self, u, y, stamps, source: str, **counts) -> Record:
        """Samples as a record named like the channels."""
        names = tuple(c.name for c in self.out_channels)
        return Record.from_samples(
            u, y, source=source, stamps_ns=stamps,
            input_names=tuple(c.name for c in self.channels), output_name=names[0],
            output_names=names if len(names) > 1 else (), **counts)

    def record(self, min_samples: int) -> Record:
        """The buffer as a record (TooFewSamplesError below ``min_samples``, saying why)."""
        stamps, u, y = self.snapshot()
        if len(y) < min_samples:
            why = (f"; {self.field_errors} message(s) were dropped because a field could "
                   f"not be read (last: {self.field_error})" if self.field_errors else "")
            raise TooFewSamplesError(f"too few samples: {len(y)} paired samples in the buffer, "
                                     f"at least {min_samples} needed (min_samples)" + why)
        return self.record_of(u, y, stamps, f"buffer of {self.node.get_fully_qualified_name()}",
                              unset_stamps=self.unset.count)

    # -- the graph -----------------------------------------------------------------------
    def check_graph(self) -> None:
        """Find publishers of another type on our topics; log rejections and jumps.

        DDS never delivers messages of another type, so they are found in the graph.
        """
        node, log = self.node, self.node.get_logger()
        for role, (topic, expected) in self.topics.items():
            for info in node.get_publishers_info_by_topic(topic):
                if info.topic_type == expected:
                    continue
                if "UNKNOWN" in info.node_name and self._unnamed_checks < UNNAMED_CHECKS:
                    # Discovery has seen the endpoint but not yet its node: name it later.
                    self._unnamed_checks += 1
                    continue
                key = (topic, f"{info.node_namespace.rstrip('/')}/{info.node_name}")
                if key not in self.type_mismatch:
                    self.type_mismatch[key] = (
                        f"{key[1]} publishes {topic} as {info.topic_type}, but the "
                        f"{role.split()[0]} is read as {expected}: its messages are not "
                        f"received (set {role.split()[0]}_type, or fix the publisher)")
                    log.error(self.type_mismatch[key])
        self._check_namesakes()
        stats = self.buffer.stats_dict()
        new = stats["rejected_out_of_order"] - self._logged["rejected_out_of_order"]
        if new > 0:
            log.warning(f"rejected {new} sample(s) stamped before their stream's last stamp "
                        f"({stats['rejected_out_of_order']} in all; see /diagnostics)")
        self._logged["rejected_out_of_order"] = stats["rejected_out_of_order"]
        for stream, old, new_t in self.buffer.jumps[self._logged["time_jumps"]:]:
            self._logged["time_jumps"] += 1
            log.warning(
                f"{'input' if stream.startswith('u') else 'output'} stamps jumped back by "
                f"{(old - new_t) / 1e9:.3f} s (a replayed bag or a restarted clock?): the "
                "samples after the jump are a new segment; identification never fits "
                "across it")

    def _check_namesakes(self) -> None:
        """Warn (once, and in /diagnostics) when another node has this node's name.

        Service calls and parameter changes would then reach either of them.
        """
        node = self.node
        me = (node.get_name(), node.get_namespace())
        count = sum(1 for n in node.get_node_names_and_namespaces() if n == me)
        if count > 1 and not self.namesakes:
            node.get_logger().warning(
                f"{count} nodes are named {node.get_fully_qualified_name()} on this ROS domain: "
                "calls to its services and parameters may reach the other one (start this one "
                "with another name: --ros-args -r __node:=NAME)")
        self.namesakes = max(count - 1, 0)

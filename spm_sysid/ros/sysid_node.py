"""``sysid_node``: record input/output topics, identify on a service call, publish.

The node is thin: messages become numbers in a
:class:`~spm_sysid.core.stream.buffer.SampleBuffer`; a snapshot goes to
:func:`spm_sysid.core.jobs.run_job` in a worker process (so the search never
blocks recording, and uses the other core); the result becomes messages.
Parameters come from the settings schema (:mod:`spm_sysid.core.settings`),
diagnostics from :mod:`spm_sysid.core.stream.diagnostics`. Interface: see
docs/ros_interface.md.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from spm_sysid_interfaces.action import Identify
from spm_sysid_interfaces.msg import NarxModel as NarxModelMsg
from spm_sysid_interfaces.msg import NarxModelSet, Prediction, Validity
from spm_sysid_interfaces.msg import ValidationReport as ValidationReportMsg
from spm_sysid_interfaces.srv import GetModel
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger

from ..core.errors import FieldPathError
from ..core.files import atomic_write_text, check_writable_file
from ..core.io.channels import check_roles, parse_channels, stream_order, topic_streams
from ..core.io.fields import UnsetStamps, default_field, extract, parse_path
from ..core.jobs import JobSettings
from ..core.narx.mimo import MIMO_SCHEMA, MimoModel, read_model_document
from ..core.narx.model import NarxModel
from ..core.online.coupled import CoupledSession, coupled_held_out_mse
from ..core.online.session import OnlineSession, held_out_mse
from ..core.progress import Progress
from ..core.record import BAG_OPTIONS, DataSpec, Record, load_record
from ..core.settings import SETTINGS, Setting, check, node_settings, parse_text
from ..core.stream.buffer import SampleBuffer
from ..core.stream.diagnostics import diagnostic_statuses, online_status
from .common import LATCHED, RELIABLE_KEEP_ALL, REQUESTS, message_class, run_node
from .typed import (
    feedback_message,
    model_message,
    model_set_message,
    prediction_message,
    report_message,
    tracked_message,
    validity_message,
)
from .worker import JobCancelledError, JobError, JobWorker

__all__ = ["LATCHED", "SysidNode", "main", "parameter_descriptor"]

#: Graph checks (1 s apart) to wait for discovery to name a publisher of a wrong type.
UNNAMED_CHECKS = 10
#: Seconds a goal's bag may take to read when ``job_timeout`` is 0 (no limit for the job).
LOAD_BOUND = 600.0

#: The action result's error codes (``spm_sysid_interfaces/action/Identify``).
Code = Identify.Result


class TooFewSamplesError(ValueError):
    """The buffer holds fewer paired samples than ``min_samples``."""


class SaveFailedError(RuntimeError):
    """The model could not be saved to ``model_path`` (so nothing was published)."""


@dataclass
class Outcome:
    """How an identification ended: an error code of :data:`Code`, the answer, the job."""

    code: int
    message: str
    result: Any = None


def parameter_descriptor(s: Setting) -> ParameterDescriptor:
    """A node parameter's descriptor from its setting (range, read-only, description)."""
    d = ParameterDescriptor(description=s.help, read_only=s.read_only)
    if s.kind is int and s.low is not None:
        d.integer_range = [IntegerRange(from_value=int(s.low), to_value=int(s.high), step=1)]
    elif s.kind is float and s.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(s.low),
                                                     to_value=float(s.high), step=0.0)]
    if s.choices:
        d.additional_constraints = "one of " + ", ".join(s.choices)
    return d


class SysidNode(Node):
    """Records signals, identifies on request, publishes the validated model."""

    def __init__(self) -> None:
        super().__init__("spm_sysid")
        for s in node_settings():
            self.declare_parameter(s.name, s.default, parameter_descriptor(s))
        # the ROS 2 demos' pattern: a change is checked in one callback, and the accepted
        # values (and the job settings built from them) are held in another
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._hold_parameters)
        p = self._params()
        self._values, self._job = p, self._check(p)

        self.channels, self.out_channels = self._channels(p)
        streams = topic_streams(self.channels)
        out_streams = topic_streams(self.out_channels)
        self._order = np.argsort(stream_order(self.channels))  # buffer -> given order
        self._out_order = np.argsort(stream_order(self.out_channels))
        self.buffer = SampleBuffer(p["buffer_capacity"], int(round(p["stamp_tolerance"] * 1e9)),
                                   resync_samples=p["resync_samples"],
                                   input_widths=[len(idx) for _, _, idx in streams],
                                   output_widths=[len(idx) for _, _, idx in out_streams])
        self._in = [(topic, self._signal(msgtype, [self.channels[i].field for i in idx]))
                    for topic, msgtype, idx in streams]
        self._out = [(topic, self._signal(msgtype, [self.out_channels[i].field for i in idx]))
                     for topic, msgtype, idx in out_streams]
        self._topics = {f"input {topic}": (topic, msgtype) for topic, msgtype, _ in streams}
        self._topics.update({f"output {topic}": (topic, msgtype)
                             for topic, msgtype, _ in out_streams})
        qos = RELIABLE_KEEP_ALL if not p["best_effort"] else QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=p["qos_depth"],
            reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
        # One executor thread does everything quickly (rclpy's multi-threaded executor
        # takes too long per message for 2 kHz). ~/identify is a coroutine that awaits
        # the worker process, so recording goes on while it runs; its group is
        # reentrant so a second request is answered (refused) meanwhile.
        services = ReentrantCallbackGroup()
        for stream, (topic, (cls, steps)) in enumerate(self._in):
            self.create_subscription(cls, topic, self._input_callback(stream, steps), qos)
        for stream, (topic, (cls, steps)) in enumerate(self._out):
            self.create_subscription(cls, topic, self._output_callback(stream, steps), qos)
        self.model_pub = self.create_publisher(String, "~/model", LATCHED)
        self.coef_pub = self.create_publisher(Float64MultiArray, "~/coefficients", LATCHED)
        self.resid_pub = self.create_publisher(Float64MultiArray, "~/residuals", LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.narx_pub = self.create_publisher(NarxModelMsg, "~/narx_model", LATCHED)
        self.models_pub = self.create_publisher(NarxModelSet, "~/narx_models", LATCHED)
        # online: each paired sample predicted and monitored with the current model
        self.pred_pub = self.create_publisher(Prediction, "~/prediction", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100,
            reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
        self.validity_pub = self.create_publisher(Validity, "~/validity", LATCHED)
        self.tracked_pub = self.create_publisher(NarxModelMsg, "~/tracked_model", LATCHED)
        self.buffer.on_pair = self._on_pair
        self.create_timer(p["tracking_period"], self._publish_tracked)
        self.create_timer(1.0, self._online_tick)
        self.report_pub = self.create_publisher(ValidationReportMsg, "~/validation", LATCHED)
        self.create_service(Trigger, "~/identify", self._on_identify, callback_group=services,
                            qos_profile=REQUESTS)
        self.create_service(GetModel, "~/get_model", self._on_get_model,
                            callback_group=services, qos_profile=REQUESTS)
        # the action shares the Trigger's name (actions live in their own namespace)
        self.action = ActionServer(self, Identify, "~/identify", self._execute_goal,
                                   goal_callback=self._on_goal,
                                   cancel_callback=self._on_cancel, callback_group=services,
                                   goal_service_qos_profile=REQUESTS,
                                   result_service_qos_profile=REQUESTS,
                                   cancel_service_qos_profile=REQUESTS)
        self.create_service(Trigger, "~/clear", self._on_clear, callback_group=services,
                            qos_profile=REQUESTS)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self.create_timer(1.0, self._check_graph)
        # Triggered from the worker's reader thread when a job ends, to wake the executor.
        self._wake = self.create_guard_condition(lambda: None)

        self._busy = threading.Lock()
        self._started: float | None = None
        self._progress: Progress | None = None
        self._model: dict | None = None  # the last model document published
        self._model_msg: NarxModelMsg | None = None
        self._report_msg: ValidationReportMsg | None = None
        self._models_msg: NarxModelSet | None = None
        self._goal = None  # the action goal being executed
        self._feedback = None  # its feedback sender
        self._cancel_requested = False
        self._online: OnlineSession | None = None
        self._online_errors = 0
        self._predictions = 0
        self._auto = {"runs": 0, "replaced": 0, "kept": 0, "failed": 0, "last": ""}
        self._auto_running = False
        self._auto_last = -math.inf  # monotonic time of the last automatic start
        self._model_time = time.monotonic()
        self._last_stamp: int | None = None
        self._restored_from: str | None = None
        self._last_error: str | None = None
        self._field_errors = 0
        self._field_error = ""  # the last message whose field could not be read, why
        self._unset = UnsetStamps()
        self._namesakes = 0
        self._type_mismatch: dict[tuple[str, str], str] = {}
        self._unnamed_checks = 0
        self._logged = {"rejected_out_of_order": 0, "time_jumps": 0}
        self.worker = JobWorker("spm_sysid.core.jobs.run:run_job", on_progress=self._on_progress,
                                on_event=self.get_logger().info)
        self.get_logger().info(
            f"recording inputs {self._describe(self.channels)} and outputs "
            f"{self._describe(self.out_channels)}; buffer of {p['buffer_capacity']} samples")
        if p["model_path"]:
            self._republish_saved(p["model_path"])

    # -- parameters: checked against the schema when set; held values are valid ---------
    def _params(self) -> dict:
        return {s.name: self.get_parameter(s.name).value for s in node_settings()}

    def _signal(self, msgtype: str, fields: list[str]):
        try:
            return message_class(msgtype), [parse_path(f or default_field(msgtype))
                                            for f in fields]
        except (FieldPathError, ValueError) as exc:
            raise ValueError(str(exc)) from None

    @staticmethod
    def _describe(channels) -> str:
        return ", ".join(f"{c.name} = {c.topic} {c.field or default_field(c.msgtype)} "
                         f"({c.msgtype})" for c in channels)

    @staticmethod
    def _channels(values: dict) -> tuple[list, list]:
        """The input and output channels the parameters name (ValueError when they clash)."""
        inputs = parse_channels(values["input_topic"], values["input_field"],
                                values["input_type"], values["input_names"])
        outputs = parse_channels(values["output_topic"], values["output_field"],
                                 values["output_type"], values["output_names"], role="output")
        check_roles(inputs, outputs)
        return inputs, outputs

    def _check(self, values: dict) -> JobSettings:
        for s in node_settings():  # the job's own settings are checked by JobSettings
            if s.group in ("node", "online"):
                check(s.name, values[s.name])
        if values["model_path"]:
            check_writable_file(values["model_path"], "model_path")
        channels, out_channels = self._channels(values)
        for name, topic in [("input_topic", c.topic) for c in channels] + [
                ("output_topic", c.topic) for c in out_channels]:
            self._check_topic(name, topic)
        return self._settings(values, channels, out_channels)

    def _check_topic(self, parameter: str, topic: str) -> None:
        """A topic name ROS accepts, or a ValueError naming the parameter."""
        from rclpy.exceptions import NameValidationException
        from rclpy.expand_topic_name import expand_topic_name
        from rclpy.validate_full_topic_name import validate_full_topic_name

        try:
            validate_full_topic_name(expand_topic_name(topic, self.get_name(),
                                                       self.get_namespace()))
        except NameValidationException as exc:
            reason = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
            shown = topic if len(topic) <= 60 else f"{topic[:40]}... ({len(topic)} characters)"
            raise ValueError(f"{parameter} {shown!r} is not a valid topic name ({reason})") \
                from None

    @staticmethod
    def _settings(values: dict, channels, out_channels) -> JobSettings:
        return JobSettings.from_values(values).for_signals(tuple(c.name for c in channels),
                                                           out_channels[0].name)

    def _check_parameters(self, changes) -> SetParametersResult:
        """Reject a parameter change that would make an identification impossible."""
        values = {**self._values, **{c.name: c.value for c in changes}}
        try:
            self._check(values)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _hold_parameters(self, changes) -> None:
        """Hold the accepted values and the job settings built from them."""
        values = {**self._values, **{c.name: c.value for c in changes}}
        self._values, self._job = values, self._check(values)

    # -- recording ---------------------------------------------------------------------
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
        except FieldPathError as exc:
            self._field_errors += 1
            self._field_error = str(exc)
            if self._field_errors == 1:
                self.get_logger().error(str(exc))
            return
        before = self._unset.count
        stamp = self._unset.stamp(stream, msg)
        if self._unset.count == 1 and before == 0:
            self.get_logger().warning(
                f"{type(msg).__name__} messages arrive with header.stamp 0 again and again "
                "(the publisher does not fill it in?): their receive times are used "
                "instead; such messages are counted in /diagnostics")
        add(self.get_clock().now().nanoseconds if stamp is None else stamp, value)

    def _check_graph(self) -> None:
        """Find publishers of another type on our topics; log rejections and jumps.

        DDS never delivers messages of another type, so they are found in the graph.
        """
        for role, (topic, expected) in self._topics.items():
            for info in self.get_publishers_info_by_topic(topic):
                if info.topic_type == expected:
                    continue
                if "UNKNOWN" in info.node_name and self._unnamed_checks < UNNAMED_CHECKS:
                    # Discovery has seen the endpoint but not yet its node: name it later.
                    self._unnamed_checks += 1
                    continue
                key = (topic, f"{info.node_namespace.rstrip('/')}/{info.node_name}")
                if key not in self._type_mismatch:
                    self._type_mismatch[key] = (
                        f"{key[1]} publishes {topic} as {info.topic_type}, but the "
                        f"{role.split()[0]} is read as {expected}: its messages are not "
                        f"received (set {role.split()[0]}_type, or fix the publisher)")
                    self.get_logger().error(self._type_mismatch[key])
        self._check_namesakes()
        stats = self.buffer.stats_dict()
        new = stats["rejected_out_of_order"] - self._logged["rejected_out_of_order"]
        if new > 0:
            self.get_logger().warning(
                f"rejected {new} sample(s) stamped before their stream's last stamp "
                f"({stats['rejected_out_of_order']} in all; see /diagnostics)")
        self._logged["rejected_out_of_order"] = stats["rejected_out_of_order"]
        for stream, old, new_t in self.buffer.jumps[self._logged["time_jumps"]:]:
            self._logged["time_jumps"] += 1
            self.get_logger().warning(
                f"{'input' if stream.startswith('u') else 'output'} stamps jumped back by "
                f"{(old - new_t) / 1e9:.3f} s (a replayed bag or a restarted clock?): the "
                "samples after the jump are a new segment; identification never fits "
                "across it")

    def _check_namesakes(self) -> None:
        """Warn (once, and in /diagnostics) when another node has this node's name.

        Service calls and parameter changes would then reach either of them.
        """
        me = (self.get_name(), self.get_namespace())
        count = sum(1 for n in self.get_node_names_and_namespaces() if n == me)
        if count > 1 and not self._namesakes:
            self.get_logger().warning(
                f"{count} nodes are named {self.get_fully_qualified_name()} on this ROS domain: "
                "calls to its services and parameters may reach the other one (start this one "
                "with another name: --ros-args -r __node:=NAME)")
        self._namesakes = max(count - 1, 0)

    # -- services and the action ----------------------------------------------------------
    def _on_clear(self, request, response):
        response.success, response.message = True, f"cleared {self.buffer.clear()} samples"
        self.get_logger().info(response.message)
        return response

    async def _on_identify(self, request, response):
        """``~/identify`` (Trigger): the action's job, answered as a paragraph."""
        out = await self._identify()
        response.success = out.code in (Code.NONE, Code.DIVERGED)
        response.message = out.message
        return response

    def _on_goal(self, goal) -> GoalResponse:
        # Every goal is accepted: a second one while one runs ends at once with BUSY and
        # the reason, which a rejection could not carry.
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle) -> CancelResponse:
        running = self._goal
        if running is not None and bytes(goal_handle.goal_id.uuid) == bytes(
                running.goal_id.uuid):
            self._cancel_requested = True
            self.worker.cancel("canceled by the client")
            self.get_logger().info("identification canceled by the client")
        return CancelResponse.ACCEPT

    async def _execute_goal(self, goal_handle) -> Identify.Result:
        """``~/identify`` (action): feedback while it runs; a typed result with a code."""
        goal = goal_handle.request
        t0 = time.monotonic()

        def feedback(progress: Progress) -> None:  # the worker's reader thread
            try:
                goal_handle.publish_feedback(feedback_message(progress, time.monotonic() - t0))
            except Exception:  # noqa: BLE001 - the goal ended meanwhile: nothing to tell
                pass

        out = await self._identify(list(goal.setting_names), list(goal.setting_values),
                                   goal.bag_path, feedback=feedback, goal=goal_handle)
        result = Identify.Result(error_code=out.code, message=out.message)
        if out.result is not None:
            self._fill(result)
        if out.code == Code.CANCELED and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif out.code in (Code.NONE, Code.DIVERGED):
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def _on_get_model(self, request, response):
        """``~/get_model``: the current model, for nodes that cannot use latched topics."""
        if self._model is None:
            response.available = False
            response.message = "no model yet: call ~/identify (or set model_path)"
            return response
        response.available = True
        self._fill(response)
        response.message = (self._size(self._model)
                            + (f", restored from {self._restored_from}"
                               if self._restored_from else ""))
        return response

    def _fill(self, answer) -> None:
        """The current model's messages and document into an action result or response."""
        if self._model_msg is not None:  # one output
            answer.model, answer.report = self._model_msg, self._report_msg
        answer.models = self._models_msg
        answer.document = json.dumps(self._model, allow_nan=False)

    @staticmethod
    def _size(doc: dict) -> str:
        """A model's size in words (one output, or several)."""
        if doc.get("schema") == MIMO_SCHEMA:
            return ", ".join(f"{o}: {len(m['terms'])} terms"
                             for o, m in zip(doc["outputs"], doc["models"]))
        return f"{len(doc['terms'])} terms"

    def _override(self, names: list[str], texts: list[str]) -> tuple[dict, JobSettings]:
        """The held values with a goal's overrides, checked by the parameters' schema."""
        if len(names) != len(texts):
            raise ValueError(f"{len(names)} setting_names but {len(texts)} setting_values")
        values = dict(self._values)
        for name, text in zip(names, texts):
            s = SETTINGS.get(name)
            if s is None or not s.node:
                raise ValueError(f"unknown setting {name!r} (the node's parameters: "
                                 "config/sysid_node.yaml)")
            if s.read_only:
                raise ValueError(f"{name} is set when the node starts; a goal cannot change it")
            values[name] = check(name, parse_text(s, text))
        return values, self._check(values)

    def _load(self, values: dict, bag_path: str) -> Record:
        """The record a job runs on: the buffer's snapshot, or a bag read like the topics."""
        if bag_path:
            spec = DataSpec(bag=bag_path, bag_options={k: values[k] for k in BAG_OPTIONS
                                                        if values.get(k)})
            return load_record(spec)
        stamps, u, y = self._snapshot()
        if len(y) < values["min_samples"]:
            why = (f"; {self._field_errors} message(s) were dropped because a field could "
                   f"not be read (last: {self._field_error})" if self._field_errors else "")
            raise TooFewSamplesError(f"too few samples: {len(y)} paired samples in the buffer, "
                                     f"at least {values['min_samples']} needed (min_samples)"
                                     + why)
        return self._record_of(u, y, stamps, f"buffer of {self.get_fully_qualified_name()}",
                               unset_stamps=self._unset.count)

    def _snapshot(self):
        """The buffer's samples with inputs and outputs in the order the parameters give."""
        stamps, u, y = self.buffer.snapshot()
        if u.ndim == 2:
            u = u[:, self._order]
        if y.ndim == 2:
            y = y[:, self._out_order]
        return stamps, u, y

    def _record_of(self, u, y, stamps, source: str, **counts) -> Record:
        names = tuple(c.name for c in self.out_channels)
        return Record.from_samples(
            u, y, source=source, stamps_ns=stamps,
            input_names=tuple(c.name for c in self.channels), output_name=names[0],
            output_names=names if len(names) > 1 else (), **counts)

    async def _identify(self, names=(), texts=(), bag_path: str = "", *, feedback=None,
                        goal=None, record: Record | None = None,
                        auto: bool = False) -> Outcome:
        """One identification for the Trigger, the action and the automatic runs.

        An outcome with its code. ``record`` (automatic runs): these samples
        instead of the buffer; ``auto``: the result is returned, not published
        (the caller compares it with the current model). A manual request
        preempts a running automatic one.
        """
        if not auto and self._auto_running:
            self.worker.cancel("preempted by a manual identification")
            await self._until(lambda: not self._busy.locked(), 10.0)
        if not self._busy.acquire(blocking=False):
            return Outcome(Code.BUSY, (
                f"an identification is already running (started "
                f"{time.monotonic() - (self._started or time.monotonic()):.1f} s ago); "
                "try again when it has finished"))
        self._goal, self._cancel_requested, self._feedback = goal, False, feedback
        try:
            try:
                values, settings = (self._override(names, texts) if names or texts
                                    else (self._values, self._job))
            except (ValueError, TypeError) as exc:
                return Outcome(Code.INVALID_SETTINGS, f"invalid settings: {exc}")
            try:
                if record is None and bag_path:  # read off the executor, with a bound
                    record = await self._off_executor(lambda: self._load(values, bag_path),
                                                      values["job_timeout"] or LOAD_BOUND)
                elif record is None:  # the buffer: on the executor, as its callbacks
                    record = self._load(values, "")
            except TooFewSamplesError as exc:
                return Outcome(Code.TOO_FEW_SAMPLES, str(exc))
            except JobCancelledError:
                return Outcome(Code.CANCELED, "canceled while reading the data; the previous "
                               "model stays published")
            except (ValueError, OSError) as exc:
                return self._failed(Code.BAD_DATA, exc)
            if not await self._worker_ready(30.0):
                return self._failed(Code.FAILED, RuntimeError(
                    "the worker process is not ready ("
                    + (self.worker.start_failure or "see the log") + ")"))
            if self._cancel_requested:
                return Outcome(Code.CANCELED, "canceled before the search started")
            self._started, self._progress = time.monotonic(), None
            self.get_logger().info(f"identifying on {len(record.y)} samples "
                                   f"({settings.criterion}, {settings.ga.generations} "
                                   "generations)")
            try:
                result = await self._run_in_worker(record, settings, values)
            except JobCancelledError as exc:
                if self._cancel_requested:
                    return Outcome(Code.CANCELED, "canceled by the client; the previous "
                                   "model stays published")
                return self._failed(Code.TIMEOUT if "job_timeout" in str(exc) else Code.FAILED,
                                    exc)
            except JobError as exc:
                code = {"DataError": Code.BAD_DATA, "BagError": Code.BAD_DATA,
                        "SettingsError": Code.INVALID_SETTINGS}.get(exc.kind, Code.FAILED)
                if code == Code.BAD_DATA and str(exc).startswith("too few samples"):
                    code = Code.TOO_FEW_SAMPLES
                return self._failed(code, exc)
            if auto:
                return Outcome(Code.NONE, result.summary("line"), result)
            try:
                self._publish_result(result, values["model_path"])
            except SaveFailedError as exc:
                return self._failed(Code.SAVE_FAILED, exc)
            message = result.summary("line")
            self.get_logger().info(f"identified: {message}")
            return Outcome(Code.DIVERGED if self._diverged(result) else Code.NONE, message,
                           result)
        except Exception as exc:  # noqa: BLE001 - any failure of the search is a refusal
            return self._failed(Code.FAILED, exc)
        finally:
            self._started = self._goal = self._feedback = None
            self._busy.release()

    @staticmethod
    def _diverged(result) -> bool:
        """The free-run simulation (of any output, coupled) left the measured range."""
        if hasattr(result, "diverged"):  # several outputs
            return bool(result.diverged)
        return result.report is not None and result.report.diverged_at is not None

    def _failed(self, code: int, exc: BaseException) -> Outcome:
        self._last_error = str(exc)
        message = f"identification failed: {exc}"
        self.get_logger().error(message)
        return Outcome(code, message)

    def _off_executor(self, fn, timeout: float) -> Future:
        """An awaitable of ``fn()`` run on a thread: its value, its error, or a timeout.

        Reading a user's path may block (a slow disk, a network mount); the
        executor goes on serving cancels, ``~/get_model`` and ``/diagnostics``
        meanwhile. A cancel ends the wait too.
        """
        done = Future()
        lock = threading.Lock()

        def settle(value=None, exc: BaseException | None = None) -> None:
            with lock:
                if done.done():
                    return
                if exc is None:
                    done.set_result(value)
                else:
                    done.set_exception(exc)
            self._wake.trigger()

        def run() -> None:
            try:
                settle(fn())
            except BaseException as exc:  # noqa: BLE001 - handed to the awaiting coroutine
                settle(exc=exc)

        def watch() -> None:
            end = time.monotonic() + timeout
            while not done.done():
                if self._cancel_requested:
                    settle(exc=JobCancelledError("canceled by the client"))
                elif time.monotonic() > end:
                    settle(exc=OSError(f"reading the data took longer than {timeout:g} s "
                                       "(job_timeout); is the path on a slow or stuck device?"))
                time.sleep(0.05)

        threading.Thread(target=run, daemon=True, name="read-data").start()
        threading.Thread(target=watch, daemon=True, name="read-data-watch").start()
        return done

    def _until(self, predicate, timeout: float) -> Future:
        """An awaitable: ``predicate()`` became true (or ``timeout`` seconds passed)."""
        done = Future()

        def wait() -> None:
            end = time.monotonic() + timeout
            while not predicate() and time.monotonic() < end:
                time.sleep(0.02)
            done.set_result(predicate())
            self._wake.trigger()

        threading.Thread(target=wait, daemon=True).start()
        return done

    def _worker_ready(self, timeout: float) -> Future:
        """An awaitable: the worker process is ready (it restarts after a cancel)."""
        ready = Future()

        def wait() -> None:
            ready.set_result(self.worker.wait_ready(timeout))
            self._wake.trigger()

        if self.worker.ready:
            ready.set_result(True)
        else:
            threading.Thread(target=wait, daemon=True).start()
        return ready

    def _run_in_worker(self, record, settings, values) -> Future:
        """The job in the worker process, as an awaitable rclpy Future.

        With ``job_timeout`` > 0 a longer job is stopped (its process replaced).
        """
        done = Future()
        extra = {"node": self.get_fully_qualified_name(),
                 "input_topic": values["input_topic"], "output_topic": values["output_topic"]}
        if values.get("output_field"):
            extra["output_field"] = values["output_field"]
        job = self.worker.submit(record, settings, metadata=extra)
        timeout = values["job_timeout"]
        timer = threading.Timer(timeout, self.worker.cancel,
                                args=(f"stopped after {timeout:g} s (job_timeout)",))
        if timeout > 0:
            timer.daemon = True
            timer.start()

        def finished(job):  # the worker's reader thread
            timer.cancel()
            if job.exception() is None:
                done.set_result(job.result())
            else:
                exc = job.exception()
                done.set_exception(exc if isinstance(exc, (JobCancelledError, JobError))
                                   else RuntimeError(str(exc)))
            self._wake.trigger()

        job.add_done_callback(finished)
        return done

    # -- results -----------------------------------------------------------------------
    def _publish_result(self, result, model_path: str) -> None:
        """Save the model (when asked), then publish it: never publish what failed to save."""
        doc = result.model.to_dict()
        if model_path:
            try:
                atomic_write_text(model_path, json.dumps(doc, indent=2, allow_nan=False) + "\n")
            except (OSError, ValueError) as exc:
                raise SaveFailedError(f"the model could not be saved to {model_path} ({exc}); "
                                 "nothing was published") from None
            self.get_logger().info(f"model saved to {model_path}")
        residuals = np.asarray(result.residuals, dtype=float)
        self._publish_model(doc, residuals)
        resid = Float64MultiArray(data=[float(e) for e in residuals.ravel()])
        if residuals.ndim == 2:  # several outputs: rows of samples, a column per output
            rows, cols = residuals.shape
            resid.layout.dim = [
                MultiArrayDimension(label="one_step_residuals", size=rows, stride=rows * cols),
                MultiArrayDimension(label="outputs: " + ",".join(doc["outputs"]), size=cols,
                                    stride=cols)]
        else:
            resid.layout.dim = [MultiArrayDimension(label="one_step_residuals",
                                                    size=len(resid.data),
                                                    stride=len(resid.data))]
        self.resid_pub.publish(resid)
        self._restored_from = self._last_error = None
        self._publish_diagnostics()

    def _publish_model(self, doc: dict, residuals=None) -> None:
        """The model on every latched topic: JSON, coefficients, typed model and report."""
        stamp = self.get_clock().now().to_msg()
        several = doc.get("schema") == MIMO_SCHEMA
        # every message before publishing anything: all or nothing
        models_msg = model_set_message(doc, residuals, stamp)
        model_msg = None if several else model_message(doc, stamp)
        report_msg = None if several else report_message(doc, residuals, stamp)
        self.model_pub.publish(String(data=json.dumps(doc, allow_nan=False)))
        parts = ([(f"{o}: ", m) for o, m in zip(doc["outputs"], doc["models"])] if several
                 else [("", doc)])
        terms = [f"{prefix}{t}" for prefix, m in parts for t in m["terms"]]
        coefs = Float64MultiArray(data=[float(c) for _, m in parts for c in m["coefficients"]])
        coefs.layout.dim = [MultiArrayDimension(label="terms: " + "; ".join(terms),
                                                size=len(terms), stride=len(terms))]
        self.coef_pub.publish(coefs)
        if not several:  # ~/narx_model and ~/validation carry one output's model
            self.narx_pub.publish(model_msg)
            self.report_pub.publish(report_msg)
        self.models_pub.publish(models_msg)
        self._model, self._model_msg, self._report_msg = doc, model_msg, report_msg
        self._models_msg = models_msg
        self._start_online(doc, residuals)

    def _republish_saved(self, path: str) -> None:
        """At start-up: publish the model saved by an earlier run again, latched.

        A file that holds no readable model (damaged, hand-edited, not JSON, numbers
        out of range, NaN anywhere) is reported and left alone; the node starts.
        """
        if not os.path.lexists(path):
            return
        try:
            _, doc = read_model_document(path)  # as saved, with its 'created' stamp
            self._publish_model(doc)
        except Exception as exc:  # noqa: BLE001 - whatever is in the file, the node starts
            self.get_logger().warning(f"model_path {path} holds no readable model ({exc}); "
                                      "nothing re-published")
            return
        self._restored_from = path
        self.get_logger().info(f"published the model saved in {path} "
                               f"({self._size(doc)}) again")

    # -- online: prediction, validity, tracking, re-identification -----------------------
    def _start_online(self, doc: dict, residuals=None) -> None:
        """A new current model: a fresh session (its monitor starts VALID)."""
        v = self._values
        self._model_time = time.monotonic()
        if not v["monitor"]:
            self._online = None
            return
        options = dict(monitor_window=v["monitor_window"], tracking=v["tracking"],
                       forgetting=v["forgetting"], sample_period=v["sample_period"],
                       gap_factor=v["gap_factor"], horizon=v["prediction_horizon"])
        try:
            if doc.get("schema") == MIMO_SCHEMA:  # one session per output
                self._online = CoupledSession(MimoModel.from_dict(doc), residuals, **options)
            else:
                self._online = OnlineSession(NarxModel.from_dict(doc), residuals,
                                             input_std=None, **options)
        except (ValueError, TypeError) as exc:  # e.g. a restored model without uncertainty
            self._online = None
            self.get_logger().warning(f"the model cannot be monitored online ({exc})")
            return
        sessions = getattr(self._online, "sessions", [self._online])
        if any(s.reference_source == "none" for s in sessions):
            self.get_logger().warning(
                "the model document carries no residual statistics (metadata.monitor: it was "
                "written by an older version); the monitor takes its residuals as white and "
                "may doubt a good model: identify again to monitor it against its own")
        self.validity_pub.publish(validity_message(self._online, self._last_stamp))

    def _on_pair(self, stamp: int, u: np.ndarray, y) -> None:
        """Each new aligned sample (the buffer calls this): predict, monitor, track."""
        self._last_stamp = stamp
        session = self._online
        if session is None:
            return
        u = u[self._order] if len(u) > 1 else u[0]
        try:
            if isinstance(session, CoupledSession):
                samples, changed = session.feed(stamp, u, np.asarray(y)[self._out_order])
                names = session.outputs
            else:
                sample = session.feed(stamp, u, y)
                samples, changed = [sample], sample is not None and sample.changed
                names = (session.model.term_space.output,)
        except Exception as exc:  # noqa: BLE001 - counted and reported, recording goes on
            self._online_errors += 1
            if self._online_errors == 1:
                self.get_logger().error(f"online prediction failed ({exc}); counted in "
                                        "/diagnostics (online_errors)")
            return
        if all(s is None for s in samples):
            return
        self._predictions += 1
        if self._predictions % self._values["prediction_every"] == 0:
            for name, sample in zip(names, samples):
                if sample is not None:
                    self.pred_pub.publish(prediction_message(sample, session.horizon,
                                                             output_name=name))
        if changed:
            st = session.state
            text = f"model validity: {st.state}" + (f" ({st.reason})" if st.reason else "")
            # one call site per severity: rclpy refuses a site whose severity changes
            if st.state == "VALID":
                self.get_logger().info(text)
            else:
                self.get_logger().warning(text)
            self.validity_pub.publish(validity_message(session, stamp))
            if st.state == "INVALID":
                self._maybe_reidentify()

    def _publish_tracked(self) -> None:
        session = self._online
        if session is None or session.tracker is None or self._model is None:
            return
        stamp = self.get_clock().now().to_msg()
        self.tracked_pub.publish(tracked_message(self._model, session.tracker, stamp))

    def _online_tick(self) -> None:
        """Every second: validity statistics, and the re-identification policy."""
        self.validity_pub.publish(validity_message(self._online, self._last_stamp))
        self._maybe_reidentify()

    def _maybe_reidentify(self) -> None:
        """Start an automatic identification when the policy says so (and it can run)."""
        v, session = self._values, self._online
        policy = v["reidentify"]
        if policy == "never" or session is None or self._busy.locked() or self._auto_running:
            return
        now = time.monotonic()
        if now - max(self._auto_last, self._model_time if policy == "periodic"
                     else -math.inf) < v["reidentify_interval"]:
            return
        if policy == "when_invalid":
            if session.state.state != "INVALID":
                return
            since = session.change_stamp()
            why = "the model became INVALID"
        else:
            since, why = None, "periodic"
        stamps, u, y = self._snapshot()
        keep = np.ones(len(y), bool) if since is None else stamps >= since
        if policy == "periodic":  # the recent samples: the last reidentify_samples * 4
            keep[:max(len(y) - 4 * v["reidentify_samples"], 0)] = False
        if int(keep.sum()) < v["reidentify_samples"]:
            return  # not enough new samples yet; checked again every second
        self._auto_last, self._auto_running = now, True
        self.executor.create_task(self._auto_identify, stamps[keep], u[keep], y[keep], why)

    async def _auto_identify(self, stamps, u, y, why: str) -> None:
        """An automatic identification, compared with the current model.

        The new model replaces the current one only when it predicts the held-out
        recent samples better (one-step MSE).
        """
        v = self._values
        hold = max(int(round(len(y) * v["reidentify_holdout"])), 20)
        fit = slice(0, len(y) - hold)
        self._auto["runs"] += 1
        self.get_logger().info(f"automatic identification {self._auto['runs']} ({why}) on "
                               f"{len(y) - hold} samples, {hold} held out")
        try:
            record = self._record_of(u[fit], y[fit], stamps[fit],
                                     f"buffer of {self.get_fully_qualified_name()} "
                                     f"(automatic: {why})")
            out = await self._identify(record=record, auto=True)
        finally:
            self._auto_running = False
        current = None if self._online is None else self._online.model
        if out.result is None or current is None:
            self._auto["failed"] += 1
            self._auto["last"] = f"failed: {out.message}"
            self.get_logger().warning(f"automatic identification failed: {out.message}")
            return
        score = coupled_held_out_mse if isinstance(current, MimoModel) else held_out_mse
        new_mse = score(out.result.model, u[-hold:], y[-hold:])
        old_mse = score(current, u[-hold:], y[-hold:])
        if new_mse < old_mse:
            try:
                self._publish_result(out.result, v["model_path"])
            except SaveFailedError as exc:
                self._auto["failed"] += 1
                self._auto["last"] = f"failed: {exc}"
                self.get_logger().error(str(exc))
                return
            self._auto["replaced"] += 1
            self._auto["last"] = (f"replaced: held-out one-step MSE {new_mse:.4g} < "
                                  f"{old_mse:.4g}")
            self.get_logger().warning(f"automatic identification replaced the model "
                                      f"(held-out one-step MSE {new_mse:.4g} vs {old_mse:.4g}"
                                      f"): {out.message}")
        else:
            self._auto["kept"] += 1
            self._auto["last"] = f"kept: held-out one-step MSE {new_mse:.4g} >= {old_mse:.4g}"
            self.get_logger().info(f"automatic identification kept the current model (held-"
                                   f"out one-step MSE {new_mse:.4g} vs {old_mse:.4g})")
        self._publish_diagnostics()

    # -- progress and diagnostics ------------------------------------------------------------
    def _on_progress(self, progress: Progress) -> None:  # the worker's reader thread
        self._progress = progress
        self.get_logger().info(progress.line())
        feedback = self._feedback
        if feedback is not None:
            feedback(progress)

    def _publish_diagnostics(self) -> None:
        statuses = diagnostic_statuses(
            self.get_fully_qualified_name(), self.buffer.stats_dict(),
            field_errors=self._field_errors, unset_stamps=self._unset.count,
            worker_ready=self.worker.ready,
            worker_restarts=self.worker.restarts,
            type_mismatches=list(self._type_mismatch.values()), namesakes=self._namesakes,
            running=None if self._started is None else (
                self._progress or Progress("checking data"), time.monotonic() - self._started),
            last_error=self._last_error, model=self._model,
            restored_from=self._restored_from,
            callback_errors=getattr(self, "callback_errors", 0),
            worker_failure=self.worker.start_failure)
        statuses.append(online_status(self.get_fully_qualified_name(), self._online,
                                      {**self._auto, "online_errors": self._online_errors}))
        msg = DiagnosticArray(status=[DiagnosticStatus(
            level=bytes([s.level]), name=s.name, message=s.message, hardware_id="spm_sysid",
            values=[KeyValue(key=k, value=v) for k, v in s.values.items()])
            for s in statuses])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def close(self) -> None:
        """Stop the worker process (a running search is killed)."""
        self.worker.close()


def main(args: list[str] | None = None) -> int:
    """Run the node until interrupted (SIGINT or SIGTERM end it within a second or two)."""
    from rclpy.exceptions import ParameterException

    # a start-up parameter of the wrong type (-p criterion:=1) is one error line too
    return run_node(SysidNode, errors=(ValueError, TypeError, ParameterException), args=args,
                    finish=lambda node, interrupted: 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

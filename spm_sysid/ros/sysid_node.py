"""``sysid_node``: record input/output topics, identify on a service call, publish.

The node is thin: messages become numbers in a :class:`SampleBuffer`, a
snapshot goes to :func:`spm_sysid.core.job.run_job` in a worker process (so the
search never blocks recording, and uses the other core), and the result becomes
messages. Interface (see docs/ros_interface.md):

* subscriptions: input (default ``/robot_arm/torque``, WrenchStamped,
  ``wrench.torque.z``) and output (default ``/robot_arm/acceleration``,
  AccelStamped, ``accel.linear.x``); topics, types and field paths are parameters
* services: ``~/identify`` and ``~/clear`` (``std_srvs/srv/Trigger``)
* latched publishers (reliable, transient-local): ``~/model`` (JSON String),
  ``~/coefficients`` and ``~/residuals`` (Float64MultiArray)
* ``/diagnostics``: buffer health, search progress, one status per correlation test
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import fields as dataclass_fields
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.task import Future
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger

from ..core.errors import FieldPathError, ModelFormatError
from ..core.files import atomic_write_text, check_writable_file
from ..core.io.fields import default_field, extract, message_stamp_ns, parse_path
from ..core.job import JobSettings
from ..core.narx.model import NarxModel
from ..core.stream.buffer import SampleBuffer
from ..tools.worker import JobCancelledError, JobWorker, WorkerDiedError
from .bag_player import message_class

__all__ = ["SysidNode", "diagnostic_statuses", "main"]

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

# -- parameters -----------------------------------------------------------------------


def _int(desc, lo, hi, read_only=False):
    return ParameterDescriptor(description=desc, read_only=read_only,
                               integer_range=[IntegerRange(from_value=lo, to_value=hi, step=1)])


def _float(desc, lo, hi, read_only=False):
    return ParameterDescriptor(description=desc, read_only=read_only,
                               floating_point_range=[FloatingPointRange(
                                   from_value=lo, to_value=hi, step=0.0)])


def _text(desc, read_only=False):
    return ParameterDescriptor(description=desc, read_only=read_only)


PARAMETERS = {
    # name: (default, descriptor)
    "input_topic": ("/robot_arm/torque", _text("input signal topic", True)),
    "input_type": ("geometry_msgs/msg/WrenchStamped", _text("input message type", True)),
    "input_field": ("", _text("field path of u (empty: the type's default)", True)),
    "output_topic": ("/robot_arm/acceleration", _text("output signal topic", True)),
    "output_type": ("geometry_msgs/msg/AccelStamped", _text("output message type", True)),
    "output_field": ("", _text("field path of y (empty: the type's default)", True)),
    "qos_depth": (1000, _int("subscription queue depth (keep-last history only)", 1, 100000,
                             True)),
    "best_effort": (False, _text("subscribe best-effort, keep-last qos_depth (for "
                                 "best-effort sensors); default: reliable, keep-all", True)),
    "buffer_capacity": (100000, _int("most sample pairs kept (oldest dropped)", 10,
                                     10_000_000, True)),
    "stamp_tolerance": (0.0005, _float("largest input/output stamp difference of a pair, s",
                                       0.0, 1.0, True)),
    "min_samples": (100, _int("fewest paired samples for an identification", 10, 10_000_000)),
    "ny": (4, _int("output lags 1..ny", 0, 20)),
    "nu": (4, _int("number of input lags", 0, 20)),
    "degree": (2, _int("polynomial degree", 1, 5)),
    "delay": (1, _int("input delay", 1, 50)),
    "constant": (False, _text("include a constant candidate term")),
    "criterion": ("aic", _text("aic, bic or pmic2")),
    "population_size": (200, _int("GA population", 2, 100000)),
    "generations": (300, _int("GA generations", 0, 100000)),
    "crossover_prob": (0.6, _float("single-point crossover probability", 0.0, 1.0)),
    "mutation_prob": (0.01, _float("per-bit mutation probability", 0.0, 1.0)),
    "spm_fraction": (0.15, _float("single parent mating fraction s", 0.0, 0.5)),
    "fitness": ("akaike", _text("roulette fitness transform: akaike, rank or window")),
    "seed": (-1, _int("GA seed (-1: a new random seed each time)", -1, 2**31 - 1)),
    "validation": ("estimation", _text("validate on 'estimation' data or a 'holdout' tail")),
    "validation_split": (0.5, _float("estimation fraction for holdout validation", 0.1, 0.9)),
    "correlation_lags": (20, _int("largest lag of the correlation tests", 1, 1000)),
    "sample_period": (0.0, _float("sampling period, s, for finding gaps (0: estimated from "
                                  "the stamps)", 0.0, 3600.0)),
    "gap_factor": (1.5, _float("a stamp difference above gap_factor periods is a gap", 1.01,
                               1000.0)),
    "resync_samples": (10, _int("in-order samples behind a stream's last stamp that make "
                                "the node accept a jump back in time", 1, 100000, True)),
    "job_timeout": (600.0, _float("seconds an identification may run before it is stopped "
                                  "(0: no limit)", 0.0, 1e6)),
    "model_path": ("", _text("save each model's JSON document here and publish it again "
                             "at start-up (empty: don't)")),
    "diagnostics_period": (1.0, _float("seconds between /diagnostics messages", 0.05, 60.0,
                                       True)),
}

_JOB_FIELDS = {f.name for f in dataclass_fields(JobSettings)} - {"extra", "progress_every"}


class SysidNode(Node):
    """Records signals, identifies on request, publishes the validated model."""

    def __init__(self) -> None:
        super().__init__("spm_sysid")
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
        self.add_on_set_parameters_callback(self._check_parameters)
        self._check_or_raise()
        p = self._params()

        self.buffer = SampleBuffer(p["buffer_capacity"], int(round(p["stamp_tolerance"] * 1e9)),
                                   resync_samples=p["resync_samples"])
        self._in = self._signal(p["input_type"], p["input_field"])
        self._out = self._signal(p["output_type"], p["output_field"])
        self._topics = {"input": (p["input_topic"], p["input_type"]),
                        "output": (p["output_topic"], p["output_type"])}
        if p["best_effort"]:
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=p["qos_depth"],
                             reliability=ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.VOLATILE)
        else:  # reliable and keep-all: a burst waits in the queue instead of being dropped
            qos = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
        # One executor thread does everything quickly (rclpy's multi-threaded executor
        # takes too long per message for 2 kHz). ~/identify is a coroutine that awaits
        # the worker process, so recording goes on while it runs; its group is
        # reentrant so a second request is answered (refused) meanwhile.
        services = ReentrantCallbackGroup()
        self.create_subscription(self._in[0], p["input_topic"], self._on_input, qos)
        self.create_subscription(self._out[0], p["output_topic"], self._on_output, qos)
        self.model_pub = self.create_publisher(String, "~/model", LATCHED)
        self.coef_pub = self.create_publisher(Float64MultiArray, "~/coefficients", LATCHED)
        self.resid_pub = self.create_publisher(Float64MultiArray, "~/residuals", LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/identify", self._on_identify, callback_group=services)
        self.create_service(Trigger, "~/clear", self._on_clear, callback_group=services)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self.create_timer(1.0, self._check_graph)
        # Triggered from the worker's reader thread when a job ends, to wake the executor.
        self._wake = self.create_guard_condition(lambda: None)

        self._busy = threading.Lock()
        self._started: float | None = None
        self._progress: tuple | None = None
        self._last_result: dict | None = None
        self._last_error: str | None = None
        self._field_errors = 0
        self._type_mismatch: dict[tuple[str, str], str] = {}
        self._logged_rejects = {"rejected_out_of_order": 0, "time_jumps": 0}
        self.worker = JobWorker("spm_sysid.core.job:run_job", on_progress=self._on_progress,
                                on_event=self.get_logger().info)
        self.get_logger().info(
            f"recording {p['input_topic']} ({p['input_type']}) and {p['output_topic']} "
            f"({p['output_type']}); buffer of {p['buffer_capacity']} pairs")
        if p["model_path"]:
            self._republish_saved(p["model_path"])

    # -- parameters ---------------------------------------------------------------------
    def _params(self) -> dict:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _signal(self, msgtype: str, field: str):
        try:
            cls = message_class(msgtype)
            steps = parse_path(field or default_field(msgtype))
        except (FieldPathError, ValueError) as exc:
            raise ValueError(str(exc)) from None
        return cls, steps

    def _settings(self, values: dict) -> JobSettings:
        s = JobSettings(**{k: values[k] for k in _JOB_FIELDS if k in values})
        s.seed = None if values.get("seed", -1) < 0 else int(values["seed"])
        s.criterion = str(s.criterion).lower()
        return s

    def _check(self, values: dict) -> None:
        self._settings(values).check()
        if values["model_path"]:
            check_writable_file(values["model_path"], "model_path")

    def _check_or_raise(self) -> None:
        self._check(self._params())

    def _check_parameters(self, changes) -> SetParametersResult:
        """Reject a parameter change that would make an identification impossible."""
        values = self._params()
        values.update({c.name: c.value for c in changes})
        try:
            self._check(values)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    # -- recording ---------------------------------------------------------------------
    def _on_input(self, msg) -> None:
        self._record(msg, self._in[1], self.buffer.add_input)

    def _on_output(self, msg) -> None:
        self._record(msg, self._out[1], self.buffer.add_output)

    def _record(self, msg, steps, add) -> None:
        try:
            value = extract(msg, steps)
        except FieldPathError as exc:
            self._field_errors += 1
            if self._field_errors == 1:
                self.get_logger().error(str(exc))
            return
        stamp = message_stamp_ns(msg)
        add(self.get_clock().now().nanoseconds if stamp is None else stamp, value)

    def _check_graph(self) -> None:
        """Find publishers of another message type on our topics (DDS never matches them)."""
        for role, (topic, expected) in self._topics.items():
            for info in self.get_publishers_info_by_topic(topic):
                if info.topic_type != expected:
                    key = (topic, f"{info.node_namespace.rstrip('/')}/{info.node_name}")
                    if key not in self._type_mismatch:
                        text = (f"{key[1]} publishes {topic} as {info.topic_type}, but the "
                                f"{role} is read as {expected}: its messages are not "
                                f"received (set {role}_type, or fix the publisher)")
                        self._type_mismatch[key] = text
                        self.get_logger().error(text)
        self._log_rejections()

    def _log_rejections(self) -> None:
        """A warning when samples were rejected as out of order or the stamps jumped."""
        stats = self.buffer.stats_dict()
        new = stats["rejected_out_of_order"] - self._logged_rejects["rejected_out_of_order"]
        if new > 0:
            self.get_logger().warning(
                f"rejected {new} sample(s) stamped before their stream's last stamp "
                f"({stats['rejected_out_of_order']} in all; see /diagnostics)")
        while self._logged_rejects["time_jumps"] < len(self.buffer.jumps):
            stream, old, new_t = self.buffer.jumps[self._logged_rejects["time_jumps"]]
            self._logged_rejects["time_jumps"] += 1
            self.get_logger().warning(
                f"{'input' if stream == 'u' else 'output'} stamps jumped back by "
                f"{(old - new_t) / 1e9:.3f} s (a replayed bag or a restarted clock?): the "
                "samples after the jump are a new segment; identification never fits "
                "across it")
        self._logged_rejects["rejected_out_of_order"] = stats["rejected_out_of_order"]

    # -- services ----------------------------------------------------------------------
    def _on_clear(self, request, response):
        removed = self.buffer.clear()
        response.success = True
        response.message = f"cleared {removed} samples"
        self.get_logger().info(response.message)
        return response

    async def _on_identify(self, request, response):
        if not self._busy.acquire(blocking=False):
            response.success = False
            response.message = (f"an identification is already running (started "
                                f"{time.monotonic() - (self._started or time.monotonic()):.1f}"
                                " s ago); try again when it has finished")
            return response
        try:
            values = self._params()
            stamps, u, y = self.buffer.snapshot()
            if len(y) < values["min_samples"]:
                response.success = False
                response.message = (f"too few samples: {len(y)} paired samples in the buffer, "
                                    f"at least {values['min_samples']} needed (min_samples)")
                return response
            settings = self._settings(values)
            settings.extra = {"node": self.get_fully_qualified_name(),
                              "input_topic": values["input_topic"],
                              "output_topic": values["output_topic"]}
            if not self.worker.wait_ready(30.0):
                raise RuntimeError("the worker process is not ready (see the log)")
            self._started = time.monotonic()
            self._progress = (0, float("nan"), 0)
            self.get_logger().info(f"identifying on {len(y)} samples "
                                   f"({settings.criterion.upper()}, population "
                                   f"{settings.population_size}, {settings.generations} "
                                   f"generations, SPM {settings.spm_fraction})")
            result = await self._run_in_worker(stamps, u, y, settings, values["job_timeout"])
            self._publish_result(result, values)
            response.success = True
            response.message = result["summary"]
            self.get_logger().info(f"identified: {result['summary']}")
            return response
        except Exception as exc:  # any failure of the search is a refusal, not a crash
            self._last_error = str(exc)
            response.success = False
            response.message = f"identification failed: {exc}"
            self.get_logger().error(response.message)
            return response
        finally:
            self._started = None
            self._busy.release()

    def _run_in_worker(self, stamps, u, y, settings, timeout: float) -> Future:
        """Submit the job to the worker process; an awaitable rclpy Future of its result.

        With ``timeout`` > 0 the job is stopped (its process killed and replaced)
        when it runs longer.
        """
        done = Future()
        job = self.worker.submit(stamps, u, y, settings)
        timer = None
        if timeout > 0:
            timer = threading.Timer(timeout, self.worker.cancel,
                                    args=(f"stopped after {timeout:g} s (job_timeout)",))
            timer.daemon = True
            timer.start()

        def finished(job):  # runs in the worker's reader thread
            if timer is not None:
                timer.cancel()
            exc = job.exception()
            if exc is None:
                done.set_result(job.result())
            elif isinstance(exc, (JobCancelledError, WorkerDiedError)):
                done.set_exception(RuntimeError(str(exc)))
            else:
                done.set_exception(exc)
            self._wake.trigger()

        job.add_done_callback(finished)
        return done

    # -- results -----------------------------------------------------------------------
    def _publish_result(self, result: dict, values: dict) -> None:
        """Save the model (when asked), then publish it: never publish what failed to save."""
        doc = result["model"]
        text = json.dumps(doc, allow_nan=False)
        if values["model_path"]:
            try:
                atomic_write_text(values["model_path"], json.dumps(doc, indent=2,
                                                                   allow_nan=False) + "\n")
            except OSError as exc:
                raise RuntimeError(f"the model could not be saved to {values['model_path']} "
                                   f"({exc}); nothing was published") from None
            self.get_logger().info(f"model saved to {values['model_path']}")
        self._publish_model(doc, text)
        resid = Float64MultiArray()
        n = len(result["residuals"])
        resid.layout.dim = [MultiArrayDimension(label="one_step_residuals", size=n, stride=n)]
        resid.data = result["residuals"]
        self.resid_pub.publish(resid)
        self._last_result = result
        self._last_error = None
        self._publish_diagnostics()

    def _publish_model(self, doc: dict, text: str) -> None:
        self.model_pub.publish(String(data=text))
        coefs = Float64MultiArray()
        coefs.layout.dim = [MultiArrayDimension(
            label="terms: " + "; ".join(doc["terms"]), size=len(doc["terms"]),
            stride=len(doc["terms"]))]
        coefs.data = [float(c) for c in doc["coefficients"]]
        self.coef_pub.publish(coefs)

    def _republish_saved(self, path: str) -> None:
        """At start-up: publish the model saved by an earlier run again, latched."""
        if not os.path.isfile(path):
            return
        try:
            doc = NarxModel.load(path).to_dict()
            doc = json.loads(Path(path).read_text())  # as saved (its own 'created' stamp)
        except (ModelFormatError, OSError, ValueError) as exc:
            self.get_logger().warning(f"model_path {path} holds no readable model ({exc}); "
                                      "nothing re-published")
            return
        self._publish_model(doc, json.dumps(doc, allow_nan=False))
        self._last_result = {"model": doc, "restored_from": path}
        self.get_logger().info(f"published the model saved in {path} "
                               f"({len(doc['terms'])} terms) again")

    # -- progress and diagnostics ------------------------------------------------------------
    def _on_progress(self, gen, best, evals) -> None:  # the worker's reader thread
        self._progress = (gen, best, evals)
        self.get_logger().info(f"search: generation {gen}, best {best:.2f}, "
                               f"{evals} structures fitted")

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray(status=diagnostic_statuses(
            self.get_fully_qualified_name(), self.buffer.stats_dict(),
            field_errors=self._field_errors, worker_ready=self.worker.ready,
            worker_restarts=self.worker.restarts,
            type_mismatches=list(self._type_mismatch.values()),
            running=None if self._started is None else (
                *(self._progress or (0, float("nan"), 0)), time.monotonic() - self._started),
            last_error=self._last_error, last_result=self._last_result))
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def close(self) -> None:
        """Stop the worker process (a running search is killed)."""
        self.worker.close()


def _kv(values: dict) -> list[KeyValue]:
    return [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]


def diagnostic_statuses(name: str, stats: dict, *, field_errors: int = 0,
                        worker_ready: bool = True, worker_restarts: int = 0,
                        type_mismatches: list[str] | None = None,
                        running: tuple | None = None, last_error: str | None = None,
                        last_result: dict | None = None) -> list[DiagnosticStatus]:
    """The node's /diagnostics statuses from plain data (buffer, identification, tests)."""
    type_mismatches = type_mismatches or []
    lost = stats["rejected_nonfinite"] + stats["rejected_out_of_order"]
    problems = []
    if lost:
        problems.append(f"{lost} rejected")
    if stats.get("time_jumps"):
        problems.append(f"{stats['time_jumps']} jump(s) back in time")
    if type_mismatches:
        problems.append("a publisher of the wrong message type")
    if not worker_ready:
        problems.append("worker not ready")
    level = DiagnosticStatus.OK
    if lost or field_errors or stats.get("time_jumps") or not worker_ready:
        level = DiagnosticStatus.WARN
    if type_mismatches:
        level = DiagnosticStatus.ERROR
    buf = DiagnosticStatus(
        level=level, name=f"{name}: buffer", hardware_id="spm_sysid",
        message=f"{stats['samples']} paired samples" + "".join(f", {p}" for p in problems),
        values=_kv(stats) + _kv({"field_errors": field_errors, "worker_ready": worker_ready,
                                 "worker_restarts": worker_restarts,
                                 "type_mismatch": "; ".join(type_mismatches)}))
    statuses = [buf]
    ident = f"{name}: identification"
    if running is not None:
        gen, best, evals, seconds = running
        statuses.append(DiagnosticStatus(
            level=DiagnosticStatus.OK, name=ident, hardware_id="spm_sysid",
            message=f"running: generation {gen}",
            values=_kv({"generation": gen, "best": f"{best:.4f}", "evaluations": evals,
                        "seconds": f"{seconds:.2f}"})))
    elif last_error:
        statuses.append(DiagnosticStatus(level=DiagnosticStatus.ERROR, name=ident,
                                         hardware_id="spm_sysid", message=last_error))
    elif last_result is not None:
        doc = last_result["model"]
        data = doc.get("metadata", {}).get("data", {})
        incomplete = bool(data.get("gaps") or data.get("skipped_segments"))
        source = (f", restored from {last_result['restored_from']}"
                  if "restored_from" in last_result else "")
        statuses.append(DiagnosticStatus(
            level=DiagnosticStatus.WARN if incomplete else DiagnosticStatus.OK, name=ident,
            hardware_id="spm_sysid",
            message=f"model with {len(doc['terms'])} terms" + (
                f", fitted around {data['gaps']} gap(s) in the data" if incomplete else "")
            + source,
            values=_kv({"criterion": (doc.get("criterion") or {}).get("name"),
                        "value": (doc.get("criterion") or {}).get("value"),
                        "mse": doc.get("mse"),
                        **{f"data_{k}": v for k, v in data.items()}})))
        for t in doc.get("metadata", {}).get("validation", {}).get("correlation_tests", []):
            statuses.append(DiagnosticStatus(
                level=DiagnosticStatus.OK if t["passed"] else DiagnosticStatus.WARN,
                name=f"{name}: correlation {t['name']}", hardware_id="spm_sysid",
                message=("inside the 95 % band" if t["passed"] else "outside the 95 % band")
                + f" ({t['fraction_inside']:.0%} of lags inside)",
                values=_kv(t)))
    return statuses


def main(args: list[str] | None = None) -> int:
    """Run the node until interrupted (SIGINT or SIGTERM end it within a second or two)."""
    rclpy.init(args=args)
    executor = SingleThreadedExecutor()
    node = None
    status = 0
    try:
        node = SysidNode()
        executor.add_node(node)
        executor.spin()
    except (ValueError, TypeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        if rclpy.ok():
            rclpy.shutdown()
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

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
import multiprocessing
import queue
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
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

from ..core.buffer import SampleBuffer
from ..core.fields import FieldPathError, default_field, extract, message_stamp_ns, parse_path
from ..core.job import JobSettings, run_job
from ..core.model import NarxModel
from .bag_player import message_class

__all__ = ["SysidNode", "main"]

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

# -- the worker process -----------------------------------------------------------------

_progress_queue = None


def _init_worker(progress_queue) -> None:
    global _progress_queue
    _progress_queue = progress_queue


def _worker_job(stamps, u, y, settings: JobSettings) -> dict:
    def progress(generation, best, evaluations):
        if _progress_queue is not None:
            _progress_queue.put((generation, best, evaluations))

    return run_job(stamps, u, y, settings, progress=progress)


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
    "model_path": ("", _text("save each model's JSON document here (empty: don't)")),
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

        self.buffer = SampleBuffer(p["buffer_capacity"], int(round(p["stamp_tolerance"] * 1e9)))
        self._in = self._signal(p["input_type"], p["input_field"])
        self._out = self._signal(p["output_type"], p["output_field"])
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
        # Triggered from the pool's thread when a job ends, to wake the executor.
        self._wake = self.create_guard_condition(lambda: None)

        self._busy = threading.Lock()
        self._started: float | None = None
        self._progress: tuple | None = None
        self._last_result: dict | None = None
        self._last_error: str | None = None
        self._field_errors = 0
        ctx = multiprocessing.get_context("spawn")  # never fork a process with DDS threads
        self._progress_queue = ctx.Queue()
        self._pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker,
                                         initargs=(self._progress_queue,))
        # start the worker now, not on the first request; diagnostics say when it is ready
        self._worker_ready = self._pool.submit(int)
        self._closing = threading.Event()
        threading.Thread(target=self._drain_progress, name="progress", daemon=True).start()
        self.get_logger().info(
            f"recording {p['input_topic']} ({p['input_type']}) and {p['output_topic']} "
            f"({p['output_type']}); buffer of {p['buffer_capacity']} pairs")

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

    def _check_or_raise(self) -> None:
        self._settings(self._params()).check()

    def _check_parameters(self, changes) -> SetParametersResult:
        """Reject a parameter change that would make an identification impossible."""
        values = self._params()
        values.update({c.name: c.value for c in changes})
        try:
            self._settings(values).check()
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
            self._started = time.monotonic()
            self._progress = (0, float("nan"), 0)
            self.get_logger().info(f"identifying on {len(y)} samples "
                                   f"({settings.criterion.upper()}, population "
                                   f"{settings.population_size}, {settings.generations} "
                                   f"generations, SPM {settings.spm_fraction})")
            try:
                result = await self._run_in_worker(stamps, u, y, settings)
            except BrokenProcessPool:
                self._restart_pool()
                raise RuntimeError("the worker process died") from None
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

    def _run_in_worker(self, stamps, u, y, settings) -> Future:
        """Submit the job to the worker process; an awaitable rclpy Future of its result."""
        done = Future()
        job = self._pool.submit(_worker_job, stamps, u, y, settings)

        def finished(job):  # runs in the pool's thread
            exc = job.exception()
            if exc is None:
                done.set_result(job.result())
            else:
                done.set_exception(exc)
            self._wake.trigger()

        job.add_done_callback(finished)
        return done

    def _restart_pool(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker,
                                         initargs=(self._progress_queue,))
        self._worker_ready = self._pool.submit(int)

    # -- results -----------------------------------------------------------------------
    def _publish_result(self, result: dict, values: dict) -> None:
        doc = result["model"]
        self.model_pub.publish(String(data=json.dumps(doc)))
        coefs = Float64MultiArray()
        coefs.layout.dim = [MultiArrayDimension(
            label="terms: " + "; ".join(doc["terms"]), size=len(doc["terms"]),
            stride=len(doc["terms"]))]
        coefs.data = [float(c) for c in doc["coefficients"]]
        self.coef_pub.publish(coefs)
        resid = Float64MultiArray()
        n = len(result["residuals"])
        resid.layout.dim = [MultiArrayDimension(label="one_step_residuals", size=n, stride=n)]
        resid.data = result["residuals"]
        self.resid_pub.publish(resid)
        self._last_result = result
        self._last_error = None
        if values["model_path"]:
            path = NarxModel.from_dict(doc).save(Path(values["model_path"]))
            self.get_logger().info(f"model saved to {path}")
        self._publish_diagnostics()

    # -- progress and diagnostics ------------------------------------------------------------
    def _drain_progress(self) -> None:
        while not self._closing.is_set():
            try:
                gen, best, evals = self._progress_queue.get(timeout=0.2)
            except queue.Empty:
                continue
            except (EOFError, OSError):
                return
            self._progress = (gen, best, evals)
            self.get_logger().info(f"search: generation {gen}, best {best:.2f}, "
                                   f"{evals} structures fitted")

    def _publish_diagnostics(self) -> None:
        stats = self.buffer.stats_dict()
        name = self.get_fully_qualified_name()
        lost = stats["rejected_nonfinite"] + stats["rejected_out_of_order"]
        buf = DiagnosticStatus(
            level=DiagnosticStatus.WARN if lost or self._field_errors else DiagnosticStatus.OK,
            name=f"{name}: buffer", hardware_id="spm_sysid",
            message=(f"{stats['samples']} paired samples" + (f", {lost} rejected" if lost
                                                              else "")),
            values=[KeyValue(key=k, value=str(v)) for k, v in stats.items()]
            + [KeyValue(key="field_errors", value=str(self._field_errors)),
               KeyValue(key="worker_ready", value=str(self._worker_ready.done()))])
        statuses = [buf]
        if self._started is not None and self._progress is not None:
            gen, best, evals = self._progress
            statuses.append(DiagnosticStatus(
                level=DiagnosticStatus.OK, name=f"{name}: identification",
                hardware_id="spm_sysid", message=f"running: generation {gen}",
                values=[KeyValue(key="generation", value=str(gen)),
                        KeyValue(key="best", value=f"{best:.4f}"),
                        KeyValue(key="evaluations", value=str(evals)),
                        KeyValue(key="seconds",
                                 value=f"{time.monotonic() - self._started:.2f}")]))
        elif self._last_error:
            statuses.append(DiagnosticStatus(level=DiagnosticStatus.ERROR,
                                             name=f"{name}: identification",
                                             hardware_id="spm_sysid", message=self._last_error))
        elif self._last_result is not None:
            doc = self._last_result["model"]
            statuses.append(DiagnosticStatus(
                level=DiagnosticStatus.OK, name=f"{name}: identification",
                hardware_id="spm_sysid",
                message=f"model with {len(doc['terms'])} terms",
                values=[KeyValue(key="criterion", value=doc["criterion"]["name"]),
                        KeyValue(key="value", value=str(doc["criterion"]["value"])),
                        KeyValue(key="mse", value=str(doc["mse"]))]))
            for t in doc["metadata"]["validation"]["correlation_tests"]:
                statuses.append(DiagnosticStatus(
                    level=DiagnosticStatus.OK if t["passed"] else DiagnosticStatus.WARN,
                    name=f"{name}: correlation {t['name']}", hardware_id="spm_sysid",
                    message=("inside the 95 % band" if t["passed"] else "outside the 95 % band")
                    + f" ({t['fraction_inside']:.0%} of lags inside)",
                    values=[KeyValue(key=k, value=str(v)) for k, v in t.items()]))
        msg = DiagnosticArray(status=statuses)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def close(self) -> None:
        """Stop the worker process and the progress thread."""
        self._closing.set()
        self._pool.shutdown(wait=False, cancel_futures=True)


def main(args: list[str] | None = None) -> int:
    """Run the node until interrupted."""
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
        executor.shutdown()
        if rclpy.ok():
            rclpy.shutdown()
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

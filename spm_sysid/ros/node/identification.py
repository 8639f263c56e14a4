"""Identifications for the node: one at a time, in the worker process, answered with a code.

:meth:`Identification.run` is what the Trigger service, the action and the
automatic re-identification all await: it checks a goal's overrides, reads a
goal's bag off the executor thread (bounded), runs the job in the worker
process (:class:`~spm_sysid.ros.worker.JobWorker`: the search never blocks
recording and uses the other core; ``job_timeout`` ends it), and returns an
:class:`Outcome`: an error code of ``Identify.Result`` decided by the type of
the exception, never by its message, and the answer in words.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node
from rclpy.task import Future
from spm_sysid_interfaces.action import Identify

from ...core.errors import TooFewSamplesError
from ...core.progress import Progress
from ...core.record import BAG_OPTIONS, DataSpec, Record, load_record, topics_read
from ..futures import Pending
from ..worker import JobCancelledError, JobError, JobTimeoutError, JobWorker
from .parameters import NodeParameters
from .publishing import SaveFailedError
from .recording import Recorder

__all__ = ["CODES", "Code", "Identification", "LOAD_BOUND", "Outcome", "code_of", "diverged"]

#: The action result's error codes (``spm_sysid_interfaces/action/Identify``).
Code = Identify.Result
#: Seconds a goal's bag may take to read when ``job_timeout`` is 0 (no limit for the job).
LOAD_BOUND = 600.0
#: An error of the job -> the answer's code, by its class or the nearest base class the
#: worker reports (``MemoryLimitError`` and every new ``DataError`` subclass included).
CODES = {"TooFewSamplesError": Code.TOO_FEW_SAMPLES, "BagError": Code.BAD_DATA,
         "DataError": Code.BAD_DATA, "SettingsError": Code.INVALID_SETTINGS,
         "MemoryLimitError": Code.INVALID_SETTINGS, "ModelFormatError": Code.BAD_DATA}


def code_of(error: JobError) -> int:
    """The answer's code of a job's error: its class's, else its nearest base class's."""
    return next((CODES[name] for name in error.kinds if name in CODES), Code.FAILED)


@dataclass
class Outcome:
    """How an identification ended: an error code of :data:`Code`, the answer, the job."""

    code: int
    message: str
    result: Any = None


def diverged(result) -> bool:
    """The free-run simulation (of any output, coupled) left the measured range."""
    return bool(result.diverged)


class Identification:
    """One identification at a time for ``node``, in a worker process.

    Parameters
    ----------
    node : Node
    params : NodeParameters
    recorder : Recorder
        The buffer a job runs on when no bag is named.
    publish : callable
        ``publish(result, model_path)``: save and publish a manual run's result;
        :class:`~spm_sysid.ros.node.publishing.SaveFailedError` when it could not be
        saved (the answer then carries ``SAVE_FAILED``).
    """

    def __init__(self, node: Node, params: NodeParameters, recorder: Recorder,
                 publish) -> None:
        self.node, self.params, self.recorder, self.publish = node, params, recorder, publish
        self.busy = threading.Lock()
        self.idle = threading.Event()  # set while no identification runs
        self.idle.set()
        self.started: float | None = None  # monotonic start of the running job
        self.progress: Progress | None = None
        self.last_error: str | None = None
        self.auto_running = False
        self.goal = None  # the action goal being executed
        self.feedback = None  # its feedback sender
        self.cancel_requested = False
        self._reading: Pending | None = None  # a goal's bag being read
        # triggered from other threads when an awaited wait ends, to wake the executor
        self._wake = node.create_guard_condition(lambda: None)
        self.worker = JobWorker("spm_sysid.core.jobs.run:run_job", on_progress=self._on_progress,
                                on_event=node.get_logger().info)

    # -- a request -----------------------------------------------------------------------
    async def run(self, names=(), texts=(), bag_path: str = "", *, feedback=None, goal=None,
                  record: Record | None = None, auto: bool = False) -> Outcome:
        """One identification for the Trigger, the action and the automatic runs.

        ``record`` (automatic runs): these samples instead of the buffer; ``auto``:
        the result is returned, not published (the caller compares it with the
        current model). A manual request preempts a running automatic one.
        """
        if not auto and self.auto_running:
            self.worker.cancel("preempted by a manual identification")
            await Pending.run(lambda: self.idle.wait(10.0), self._wake.trigger).future
        if not self.busy.acquire(blocking=False):
            if auto:
                self.release_automatic()
            return Outcome(Code.BUSY, (
                f"an identification is already running (started "
                f"{time.monotonic() - (self.started or time.monotonic()):.1f} s ago); "
                "try again when it has finished"))
        self.idle.clear()
        self.goal, self.cancel_requested, self.feedback = goal, False, feedback
        try:
            return await self._run(names, texts, bag_path, record, auto)
        except Exception as exc:  # noqa: BLE001 - any failure of the search is a refusal
            return self._failed(Code.FAILED, exc)
        finally:
            self.started = self.goal = self.feedback = None
            if auto:
                self.release_automatic()
            self.busy.release()
            self.idle.set()

    async def _run(self, names, texts, bag_path: str, record, auto: bool) -> Outcome:
        try:
            values, settings = (self.params.override(names, texts) if names or texts
                                else (self.params.values, self.params.job))
        except (ValueError, TypeError) as exc:
            return Outcome(Code.INVALID_SETTINGS, f"invalid settings: {exc}")
        record = await self._load(values, bag_path, record)
        if isinstance(record, Outcome):
            return record
        if not await self._worker_ready(30.0):
            return self._failed(Code.FAILED, RuntimeError(
                "the worker process is not ready ("
                + (self.worker.start_failure or "see the log") + ")"))
        if self.cancel_requested:
            return Outcome(Code.CANCELED, "canceled before the search started")
        self.started, self.progress = time.monotonic(), None
        self.node.get_logger().info(f"identifying on {len(record.y)} samples "
                                    f"({settings.criterion}, {settings.ga.generations} "
                                    "generations)")
        result = await self._search(record, settings, values)
        if isinstance(result, Outcome):
            return result
        if auto:
            return Outcome(Code.NONE, result.summary("line"), result)
        try:
            self.publish(result, values["model_path"])
        except SaveFailedError as exc:  # the model could not be saved: nothing published
            return self._failed(Code.SAVE_FAILED, exc)
        message = result.summary("line")
        self.node.get_logger().info(f"identified: {message}")
        return Outcome(Code.DIVERGED if diverged(result) else Code.NONE, message, result)

    async def _load(self, values: dict, bag_path: str, record):
        """The record: as given, read from the bag, or the buffer's; an Outcome on failure."""
        try:
            if record is None and bag_path:  # read off the executor, with a bound
                try:
                    return await self._off_executor(lambda: self._bag(values, bag_path),
                                                    values["job_timeout"] or LOAD_BOUND)
                finally:
                    self._reading = None
            if record is None:  # the buffer: on the executor, as its callbacks
                return self.recorder.record(values["min_samples"])
            return record
        except TooFewSamplesError as exc:
            return Outcome(Code.TOO_FEW_SAMPLES, str(exc))
        except JobCancelledError:
            return Outcome(Code.CANCELED, "canceled while reading the data; the previous "
                           "model stays published")
        except (ValueError, OSError) as exc:
            return self._failed(Code.BAD_DATA, exc)

    async def _search(self, record, settings, values: dict):
        """The job in the worker process: its result, or the Outcome of its failure."""
        try:
            return await self._in_worker(record, settings, values)
        except JobTimeoutError as exc:
            return self._failed(Code.TIMEOUT, exc)
        except JobCancelledError as exc:
            if self.cancel_requested:
                return Outcome(Code.CANCELED, "canceled by the client; the previous "
                               "model stays published")
            return self._failed(Code.FAILED, exc)
        except JobError as exc:
            return self._failed(code_of(exc), exc)

    def can_start_automatic(self) -> bool:
        """No identification runs, manual or automatic: an automatic one may start."""
        return not self.busy.locked() and not self.auto_running

    def reserve_automatic(self) -> bool:
        """Reserve the next run for an automatic identification (False: one runs already).

        The reservation ends when that run (``run(..., auto=True)``) ends.
        """
        if not self.can_start_automatic():
            return False
        self.auto_running = True
        return True

    def release_automatic(self) -> None:
        """End the reservation of :meth:`reserve_automatic` (its run ended, or never began)."""
        self.auto_running = False

    def cancel(self, goal_handle) -> None:
        """Cancel the running goal when ``goal_handle`` is it (the search is ended at once)."""
        running = self.goal
        if running is not None and bytes(goal_handle.goal_id.uuid) == bytes(
                running.goal_id.uuid):
            self.cancel_requested = True
            reading = self._reading
            if reading is not None:  # a bag being read: the wait ends now
                reading.settle(exc=JobCancelledError("canceled by the client"))
            self.worker.cancel("canceled by the client")
            self.node.get_logger().info("identification canceled by the client")

    def close(self) -> None:
        """Stop the worker process (a running search is killed)."""
        self.worker.close()

    # -- helpers -------------------------------------------------------------------------
    def _bag(self, values: dict, bag_path: str) -> Record:
        """A bag read like the topics (the node's topics and fields)."""
        spec = DataSpec(bag=bag_path, bag_options={k: values[k] for k in BAG_OPTIONS
                                                    if values.get(k) not in (None, "")})
        return load_record(spec)

    def _failed(self, code: int, exc: BaseException) -> Outcome:
        self.last_error = str(exc)
        message = f"identification failed: {exc}"
        self.node.get_logger().error(message)
        return Outcome(code, message)

    def _on_progress(self, progress: Progress) -> None:  # the worker's reader thread
        self.progress = progress
        self.node.get_logger().info(progress.line())
        feedback = self.feedback
        if feedback is not None:
            feedback(progress)

    def _off_executor(self, fn, timeout: float) -> Future:
        """An awaitable of ``fn()`` run on a thread: its value, its error, or a timeout.

        Reading a user's path may block (a slow disk, a network mount); the
        executor goes on serving cancels, ``~/get_model`` and ``/diagnostics``
        meanwhile. A cancel (:meth:`cancel`) ends the wait at once.
        """
        self._reading = Pending.run(
            fn, self._wake.trigger, timeout=timeout,
            on_timeout=lambda: OSError(f"reading the data took longer than {timeout:g} s "
                                       "(job_timeout); is the path on a slow or stuck "
                                       "device?"))
        return self._reading.future

    def _worker_ready(self, timeout: float) -> Future:
        """An awaitable: the worker process is ready (it restarts after a cancel)."""
        if self.worker.ready:
            pending = Pending(self._wake.trigger)
            pending.settle(True)
            return pending.future
        return Pending.run(lambda: self.worker.wait_ready(timeout), self._wake.trigger).future

    def _in_worker(self, record, settings, values) -> Future:
        """The job in the worker process, as an awaitable rclpy Future.

        With ``job_timeout`` > 0 a longer job is stopped (its process replaced).
        """
        pending = Pending(self._wake.trigger)
        extra = {"node": self.node.get_fully_qualified_name(),
                 "input_topic": values["input_topic"], "output_topic": values["output_topic"]}
        if values.get("output_field"):
            extra["output_field"] = values["output_field"]
        extra["topics"] = topics_read(values)  # validate --bag reads another bag so
        job = self.worker.submit(record, settings, metadata=extra)
        timeout = values["job_timeout"]
        timer = threading.Timer(timeout, self.worker.cancel,
                                args=(f"stopped after {timeout:g} s (job_timeout)",
                                      JobTimeoutError))
        if timeout > 0:
            timer.daemon = True
            timer.start()

        def finished(job):  # the worker's reader thread
            timer.cancel()
            exc = job.exception()
            if exc is None:
                pending.settle(job.result())
            else:
                pending.settle(exc=exc if isinstance(exc, (JobCancelledError, JobError))
                               else RuntimeError(str(exc)))

        job.add_done_callback(finished)
        return pending.future

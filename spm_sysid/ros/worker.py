"""The node's job worker: its own process, cancelled, timed out, never orphaned.

The ROS node (:mod:`spm_sysid.ros.sysid_node`) runs each identification here so
the search never blocks recording and uses the other core. The module uses no
ROS itself (it is plain process management), so it is tested without ROS. The
worker is a plain child process (``python -m spm_sysid.ros.worker``) talking
over its stdin/stdout pipes with
pickled messages; no multiprocessing pool, queue or resource tracker is
involved, so nothing is left behind:

* the worker ends itself when its stdin closes (the parent died, even by
  ``kill -9``) and, on Linux, also gets SIGKILL when the parent dies
  (``PR_SET_PDEATHSIG``; every worker is started from one thread that lives as
  long as the parent, since the signal follows the starting thread);
* :meth:`JobWorker.cancel` kills a running job (a stuck search, a job timeout,
  shutdown) and starts a fresh worker;
* a worker that dies is noticed at once (its pipe closes), the job gets an
  error, and a new worker is started.

Messages from the worker: ``("ready",)``, ``("progress", *values)``,
``("result", value)``, ``("error", text, the exception's class names, nearest first)``.
"""

from __future__ import annotations

import os
import pickle
import queue
import signal
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

__all__ = ["JobCancelledError", "JobError", "JobTimeoutError", "JobWorker", "WorkerDiedError"]

_HEADER = struct.Struct("!Q")
#: Longest wait (seconds) before restarting a worker that keeps dying while it starts.
MAX_BACKOFF = 60.0


class WorkerDiedError(RuntimeError):
    """The worker process ended while running a job."""


class JobCancelledError(RuntimeError):
    """The job was cancelled (timeout, shutdown or a user's request)."""


class JobTimeoutError(JobCancelledError):
    """The job was cancelled because it ran longer than its time limit."""


class JobError(RuntimeError):
    """The job raised; ``kinds``: its exception's class name and its bases', nearest first.

    (``("TooFewSamplesError", "DataError", "ValueError", ...)``: the node maps the
    nearest it knows to an answer's code.)
    """

    def __init__(self, message: str, kinds: tuple[str, ...] | str = ()) -> None:
        super().__init__(message)
        self.kinds = (kinds,) if isinstance(kinds, str) else tuple(kinds)

    @property
    def kind(self) -> str:
        """The exception's own class name ('' when unknown)."""
        return self.kinds[0] if self.kinds else ""


class _Spawner:
    """Starts the worker processes, all from one thread that lives as long as this process.

    Linux sends a child its parent-death signal (:func:`_die_with_parent`) when the
    *thread* that started it ends, not the process. A worker started by a cancel on
    a timer's thread (a job timeout) or by a dead worker's reader thread was killed
    as soon as that thread returned, if it had asked for the signal by then: the next
    job died with SIGKILL.
    """

    def __init__(self) -> None:
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def popen(self, *args: Any, **kwargs: Any) -> subprocess.Popen:
        """``subprocess.Popen(*args, **kwargs)``, run on the spawning thread."""
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._serve, name="worker-spawner",
                                                daemon=True)
                self._thread.start()
        if threading.current_thread() is self._thread:
            return subprocess.Popen(*args, **kwargs)
        started: Future = Future()
        self._requests.put((args, kwargs, started))
        return started.result()

    def _serve(self) -> None:
        while True:
            args, kwargs, started = self._requests.get()
            try:
                started.set_result(subprocess.Popen(*args, **kwargs))
            except BaseException as exc:  # handed to the caller, who raises it
                started.set_exception(exc)


_SPAWNER = _Spawner()


def _send(stream, message: Any) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _recv(stream) -> Any:
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError
    (size,) = _HEADER.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError
    return pickle.loads(data)


class JobWorker:
    """One worker process that runs ``function(*args, **kwargs, progress=callback)`` per job.

    Parameters
    ----------
    function : str
        ``"package.module:name"`` of the job function, imported in the worker.
    on_progress : callable, optional
        Called (in a reader thread) with the values the job reports.
    on_event : callable, optional
        Called with a short text when the worker starts, dies or restarts.
    env : dict, optional
        Environment of the worker process (default: this process's).
    """

    def __init__(self, function: str, on_progress: Callable[..., None] | None = None,
                 on_event: Callable[[str], None] | None = None,
                 env: dict[str, str] | None = None) -> None:
        self.function = function
        self.on_progress = on_progress
        self.on_event = on_event or (lambda text: None)
        self.env = env
        self.restarts = 0
        #: Why the last worker died before it was ready ('' once one is ready).
        self.start_failure = ""
        self._failures = 0  # consecutive deaths before "ready": the back-off's exponent
        self._lock = threading.Lock()
        self._closing = False
        self._proc: subprocess.Popen | None = None
        self._ready = threading.Event()
        self._job: Future | None = None
        self._retry: threading.Timer | None = None
        self._start()

    # -- state ---------------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        """True when a live worker waits for (or runs) jobs."""
        return self._ready.is_set() and self._proc is not None and self._proc.poll() is None

    @property
    def busy(self) -> bool:
        return self._job is not None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def wait_ready(self, timeout: float | None = None) -> bool:
        return self._ready.wait(timeout)

    # -- jobs ------------------------------------------------------------------------------
    def submit(self, *args: Any, **kwargs: Any) -> Future:
        """Start ``function(*args, **kwargs, progress=...)``; a Future of its result.

        It fails with WorkerDiedError or JobCancelledError when the process dies or
        the job is cancelled, and with :class:`JobError` when the job raises.
        """
        with self._lock:
            if self._job is not None:
                raise RuntimeError("the worker is already running a job")
            if self._proc is None or self._proc.poll() is not None:
                raise WorkerDiedError("the worker process is not running")
            self._job = Future()
            job = self._job
            try:
                _send(self._proc.stdin, ("job", args, kwargs))
            except (BrokenPipeError, OSError):
                self._job = None
                raise WorkerDiedError("the worker process is not running") from None
        return job

    def cancel(self, reason: str = "cancelled",
               error: type[JobCancelledError] = JobCancelledError) -> None:
        """Kill the running job's process and start a fresh worker.

        The old process is retired and the new one started before the job is
        answered, so a job submitted from the answer's callback goes to the new
        worker, never to the dying one. The job fails with ``error(reason)``.
        """
        with self._lock:
            proc, job, self._job = self._proc, self._job, None
            if job is None or job.done():
                return  # nothing runs: the worker stays as it is
            self._ready.clear()
            self._proc = None  # its reader thread sees it replaced and stays quiet
        if proc is not None:
            self._kill(proc)
        with self._lock:
            if not self._closing and self._proc is None:
                self.restarts += 1
                self._start()
        job.set_exception(error(reason))

    def close(self, timeout: float = 1.0) -> None:
        """End the worker (a running job is killed); waits at most about ``timeout``."""
        self._closing = True
        with self._lock:
            proc, job, self._job = self._proc, self._job, None
            if self._retry is not None:
                self._retry.cancel()
        if job is not None and not job.done():
            job.set_exception(JobCancelledError("the node is shutting down"))
        if proc is not None:
            self._kill(proc, timeout)

    # -- process management --------------------------------------------------------------
    def _start(self) -> None:
        self._ready.clear()
        self._retry = None
        self._proc = _SPAWNER.popen(
            [sys.executable, "-m", "spm_sysid.ros.worker", self.function],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            env=self.env, start_new_session=False)
        self._proc.last_line = ""
        threading.Thread(target=self._read, args=(self._proc,), name="worker-reader",
                         daemon=True).start()
        threading.Thread(target=self._relay, args=(self._proc,), name="worker-stderr",
                         daemon=True).start()

    @staticmethod
    def _relay(proc: subprocess.Popen) -> None:
        """Pass the worker's stderr on to ours, keeping its last line (why it died)."""
        for line in proc.stderr:
            sys.stderr.buffer.write(line)
            sys.stderr.flush()
            if line.strip():
                proc.last_line = line.decode(errors="replace").strip()[:300]

    @staticmethod
    def _status(proc: subprocess.Popen) -> str:
        code = proc.returncode
        if code is not None and code < 0:
            try:
                return f"exit status {code}, {signal.Signals(-code).name}"
            except ValueError:
                pass
        return f"exit status {code}"

    @staticmethod
    def _kill(proc: subprocess.Popen, timeout: float = 1.0) -> None:
        if proc.poll() is None:
            proc.kill()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:  # pragma: no cover - SIGKILL does not wait
            pass

    def _handle(self, proc: subprocess.Popen, message: tuple) -> None:
        """One message of the worker: ready, progress, or the job's result or error."""
        kind = message[0]
        if kind == "ready":
            proc.was_ready = True
            self._failures, self.start_failure = 0, ""
            self._ready.set()
            self.on_event(f"worker process {proc.pid} ready")
        elif kind == "progress" and self.on_progress is not None:
            self.on_progress(*message[1:])
        elif kind in ("result", "error"):
            with self._lock:
                job, self._job = self._job, None
            if job is not None and not job.done():
                if kind == "result":
                    job.set_result(message[1])
                else:
                    job.set_exception(JobError(*message[1:3]))

    def _read(self, proc: subprocess.Popen) -> None:
        """Reader thread of one worker process: results, progress, and its death."""
        while True:
            try:
                message = _recv(proc.stdout)
            except (EOFError, OSError, pickle.UnpicklingError):
                break
            self._handle(proc, message)
        proc.wait()
        with self._lock:
            if proc is not self._proc:
                return  # an old process, already replaced
            self._ready.clear()
            job, self._job = self._job, None
            if self._closing:
                self._answer_died(job, proc)
                return
            self.restarts += 1
            if getattr(proc, "was_ready", False):
                self.on_event(f"worker process {proc.pid} ended ({self._status(proc)}); "
                              "starting a new one")
                self._start()
            else:  # it dies while starting: back off (1, 2, 4 ... 60 s), say why
                self._failures += 1
                delay = min(2.0 ** (self._failures - 1), MAX_BACKOFF)
                why = f": {proc.last_line}" if getattr(proc, "last_line", "") else ""
                self.start_failure = (f"the worker process died while starting "
                                      f"({self._status(proc)}{why}); {self._failures} "
                                      f"failed start(s) in a row")
                self.on_event(f"{self.start_failure}; next try in {delay:g} s")
                self._retry = threading.Timer(delay, self._retry_start)
                self._retry.daemon = True
                self._retry.start()
        self._answer_died(job, proc)

    def _answer_died(self, job: Future | None, proc: subprocess.Popen) -> None:
        if job is not None and not job.done():
            job.set_exception(WorkerDiedError(
                f"the worker process died ({self._status(proc)})"))

    def _retry_start(self) -> None:
        with self._lock:
            if not self._closing and self._proc is not None and self._proc.poll() is not None:
                self._start()


# -- the worker process side -----------------------------------------------------------


def _die_with_parent() -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def _worker_main(function: str) -> int:
    import importlib

    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when we stop
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # stray prints must not corrupt the channel
    inp = os.fdopen(0, "rb")
    module, name = function.split(":")
    mod = importlib.import_module(module)
    func = getattr(mod, name)
    if callable(getattr(mod, "warm_up", None)):
        mod.warm_up()  # e.g. load compiled kernels now, not inside the first job's time
    jobs: queue.Queue = queue.Queue()

    def read_jobs() -> None:
        while True:
            try:
                jobs.put(_recv(inp))
            except (EOFError, OSError):
                os._exit(0)  # the parent is gone (or closed us): end now, even mid-job

    threading.Thread(target=read_jobs, daemon=True).start()
    lock = threading.Lock()

    def progress(*values: Any) -> None:
        with lock:
            _send(out, ("progress", *values))

    with lock:
        _send(out, ("ready",))
    while True:
        _, args, kwargs = jobs.get()
        try:
            result = func(*args, **kwargs, progress=progress)
            reply = ("result", result)
        except Exception as exc:  # reported to the parent as the job's error
            reply = ("error", str(exc) or type(exc).__name__,
                     tuple(c.__name__ for c in type(exc).__mro__))
        with lock:
            _send(out, reply)


if __name__ == "__main__":  # pragma: no cover - started by JobWorker
    sys.exit(_worker_main(sys.argv[1]))

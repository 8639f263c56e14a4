"""Running many independent tasks: on this machine, or on a Dask cluster.

The study and the batch command hand their tasks here. Without a scheduler the
tasks run on a local process pool (one process per core; in this process when
``workers == 1``); with ``scheduler="tcp://HOST:PORT"`` they run on an existing
Dask cluster (``dask`` and ``distributed``, the ``dask`` extra). Either way:

* a task is a picklable function of ``(task, shared)``; ``shared`` (e.g. the
  data) is sent once (Dask: scattered to every worker) rather than with each task;
* every task ends with a result or an error, never silently: a task that
  raises is retried ``retries`` times and then reported with its error; a worker
  process that dies takes its tasks with it -- they are run again (locally on a
  new pool, on Dask by the scheduler), and reported if they keep failing;
* ``on_done`` is called as each task finishes (partial results can be written
  at once), in completion order; the caller orders the results by task key;
* every call of :func:`run_tasks` is a *job* with its own id: its Dask keys are
  ``spm-sysid-JOB-KEY``, so two jobs on one cluster at the same time never share
  a key (Dask would hand the second the first one's results), and every result
  comes back with the job id and task key it was computed for, checked on arrival;
* a scheduler address is checked before anything is sent: a deadline of
  :data:`CONNECT_TIMEOUT` seconds for an answer, and the answer must come from a
  Dask scheduler (a web server at that port is an error, not a hang);
* an interrupted job (Ctrl-C, or SIGTERM, which the command line turns into the
  same) ends its local worker processes before it returns.
"""

from __future__ import annotations

import traceback
import uuid
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

__all__ = ["CONNECT_TIMEOUT", "TaskOutcome", "check_scheduler", "run_tasks"]

#: Seconds to wait for a Dask scheduler's answer (``SPM_SYSID_DASK_CONNECT_TIMEOUT``).
CONNECT_TIMEOUT = float(__import__("os").environ.get("SPM_SYSID_DASK_CONNECT_TIMEOUT", "30"))


@dataclass
class TaskOutcome:
    """How one task ended: ``result``, or ``error`` (text) after ``attempts`` tries."""

    key: str
    result: Any = None
    error: str | None = None
    attempts: int = 1

    @property
    def ok(self) -> bool:
        return self.error is None


def _call(fn: Callable, task: Any, shared: Any, job: str = "", key: str = "") -> Any:
    """Run one task; the result travels with the job id and key it belongs to."""
    return job, key, fn(task, shared)


def _unwrap(value: Any, job: str, key: str) -> Any:
    """The task's result, after checking that it is this job's and this task's."""
    if not (isinstance(value, tuple) and len(value) == 3 and value[:2] == (job, key)):
        got = value[:2] if isinstance(value, tuple) and len(value) == 3 else "?"
        raise RuntimeError(f"the result for task {key} belongs to another job or task ({got}); "
                           "it was not used")
    return value[2]


def run_tasks(
    fn: Callable[[Any, Any], Any],
    tasks: Mapping[str, Any],
    *,
    shared: Any = None,
    scheduler: str | None = None,
    workers: int = 0,
    retries: int = 2,
    on_done: Callable[[TaskOutcome], None] | None = None,
) -> dict[str, TaskOutcome]:
    """Run ``fn(task, shared)`` for every task; returns key -> outcome.

    Parameters
    ----------
    fn : callable
        A module-level (picklable) function.
    tasks : mapping
        Key (a name, unique) -> task (the first argument of ``fn``).
    shared : object
        Sent once to every worker.
    scheduler : str, optional
        A Dask scheduler address (``tcp://host:port``); None: this machine.
    workers : int
        Local processes (0: one per core; 1: in this process). Ignored with Dask.
    retries : int
        Extra attempts for a task that fails.
    on_done : callable, optional
        Called with each outcome as it arrives.
    """
    done = on_done or (lambda outcome: None)
    job = uuid.uuid4().hex[:12]
    if scheduler:
        return _run_dask(fn, tasks, shared, scheduler, retries, done, job)
    import os

    workers = workers or os.cpu_count() or 1
    if workers == 1:
        return _run_here(fn, tasks, shared, retries, done)
    return _run_pool(fn, tasks, shared, workers, retries, done, job)


def _run_here(fn, tasks, shared, retries, done) -> dict[str, TaskOutcome]:
    """The tasks one after another in this process; an interrupt stops before the next.

    Ctrl-C's KeyboardInterrupt is raised wherever the main thread is; raised inside a
    finaliser (a ``__del__``, a weakref callback) or in code that catches it, it is
    lost, and the job would run on. So the handlers of SIGINT and SIGTERM also leave a
    mark, checked before each task: such an interrupt still stops the job there.
    """
    import signal
    import threading

    marks: list[int] = []
    before = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(sig)
            if callable(handler):  # not ignored (a background job's SIGINT), not the default

                def marking(signum, frame, handler=handler):
                    marks.append(signum)
                    handler(signum, frame)

                before[sig] = signal.signal(sig, marking)
    try:
        out = {}
        for key, task in tasks.items():
            if marks:
                raise KeyboardInterrupt
            out[key] = _attempt_here(fn, key, task, shared, retries)
            done(out[key])
        return out
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def _attempt_here(fn, key, task, shared, retries) -> TaskOutcome:
    """Run a task in this process, with retries."""
    for attempt in range(1, retries + 2):
        try:
            return TaskOutcome(key, fn(task, shared), None, attempt)
        except Exception:  # noqa: BLE001 - reported per task
            error = traceback.format_exc(limit=3).strip().splitlines()[-1]
    return TaskOutcome(key, None, error, retries + 1)


def _run_pool(fn, tasks, shared, workers, retries, done, job) -> dict[str, TaskOutcome]:
    out: dict[str, TaskOutcome] = {}
    attempts = dict.fromkeys(tasks, 0)
    pending = list(tasks)
    while pending:
        pool = ProcessPoolExecutor(max_workers=workers, initializer=_worker_signals)
        try:
            pending = _pool_round(pool, fn, tasks, shared, pending, attempts, retries, done,
                                  out, job)
        except BaseException:  # interrupted (Ctrl-C, SIGTERM): no worker left behind
            _stop_pool(pool)
            raise
        pool.shutdown(wait=True, cancel_futures=True)
    return out


def _pool_round(pool, fn, tasks, shared, keys, attempts, retries, done, out, job) -> list:
    """Submit ``keys`` to ``pool`` and collect them; the keys to run again on a new pool."""
    futures = {}
    for key in keys:
        attempts[key] += 1
        futures[pool.submit(_call, fn, tasks[key], shared, job, key)] = key
    pending = []
    broken = False
    while futures:
        finished, _ = wait(futures, return_when=FIRST_COMPLETED)
        for fut in finished:
            key = futures.pop(fut)
            outcome = _outcome(fut, job, key, attempts[key])
            broken |= outcome is None  # a worker process died: run its task again
            if outcome is None or (not outcome.ok and attempts[key] <= retries):
                if attempts[key] <= retries:
                    pending.append(key)
                    continue
                outcome = outcome or TaskOutcome(
                    key, None, "the worker process died (every attempt)", attempts[key])
            out[key] = outcome
            done(outcome)
        if broken:  # the pool is unusable: collect what is left and start a new one
            pending += _collect_finished(futures, job, attempts, done, out)
            futures = {}
    return pending


def _outcome(fut, job, key: str, attempt: int) -> TaskOutcome | None:
    """A finished future's outcome (an error counted per task); None when its worker died."""
    try:
        return TaskOutcome(key, _unwrap(fut.result(), job, key), None, attempt)
    except BrokenProcessPool:
        return None
    except Exception as exc:  # noqa: BLE001 - reported per task
        return TaskOutcome(key, None, f"{type(exc).__name__}: {exc}", attempt)


def _collect_finished(futures: dict, job, attempts: dict, done, out: dict) -> list:
    """Of a broken pool's futures, keep the finished ones; the keys to run again."""
    again = []
    for fut, key in futures.items():
        if fut.done() and not fut.exception():
            out[key] = TaskOutcome(key, _unwrap(fut.result(), job, key), None, attempts[key])
            done(out[key])
        else:
            again.append(key)
    return again


def _worker_signals() -> None:
    """Pool workers end on SIGTERM at once (the parent's handler is for the parent)."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """End a pool's worker processes now (they may be in the middle of long tasks)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(5)
        if p.is_alive():  # pragma: no cover - SIGTERM ignored
            p.kill()


def check_scheduler(address: str, timeout: float = CONNECT_TIMEOUT) -> None:
    """Check that a Dask scheduler answers at ``address`` within ``timeout`` seconds.

    Raises
    ------
    RuntimeError
        Dask is not installed, nothing answers, or what answers is not a Dask
        scheduler (e.g. a web server): one clear message instead of a hang.
    """
    import asyncio

    try:
        from distributed.comm import connect
    except ImportError:  # pragma: no cover - the dask extra is not installed
        raise RuntimeError("--scheduler needs Dask: pip install 'spm_sysid[dask]' "
                           "(dask and distributed)") from None

    async def identity():
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            await comm.close()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except (TimeoutError, asyncio.TimeoutError):
        raise RuntimeError(f"no Dask scheduler answered at {address} within {timeout:g} s "
                           "(something listens there, but it is not a Dask scheduler?)") from None
    except (OSError, ValueError, TypeError) as exc:
        raise RuntimeError(f"cannot connect to a Dask scheduler at {address}: {exc}") from None
    if not (isinstance(reply, dict) and reply.get("type") == "Scheduler"):
        raise RuntimeError(f"{address} answered, but not as a Dask scheduler")


def _run_dask(fn, tasks, shared, scheduler, retries, done, job) -> dict[str, TaskOutcome]:
    check_scheduler(scheduler)
    from distributed import Client, as_completed

    out: dict[str, TaskOutcome] = {}
    with Client(scheduler, timeout=CONNECT_TIMEOUT) as client:
        shared_f = client.scatter(shared, broadcast=True) if shared is not None else None
        keys = list(tasks)
        futures = client.map(_call, [fn] * len(keys), [tasks[k] for k in keys],
                             [shared_f] * len(keys), [job] * len(keys), keys,
                             key=[f"spm-sysid-{job}-{k}" for k in keys],
                             retries=retries, pure=False)
        by_future = dict(zip(futures, keys))
        for fut in as_completed(futures):
            key = by_future[fut]
            if fut.status == "finished":
                try:
                    outcome = TaskOutcome(key, _unwrap(fut.result(), job, key), None, 1)
                except RuntimeError as exc:
                    outcome = TaskOutcome(key, None, str(exc), 1)
            else:
                exc = fut.exception()
                outcome = TaskOutcome(key, None, f"{type(exc).__name__}: {exc}", retries + 1)
            out[key] = outcome
            done(outcome)
    return out

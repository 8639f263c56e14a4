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
  at once), in completion order; the caller orders the results by task key.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

__all__ = ["TaskOutcome", "run_tasks"]


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


def _call(fn: Callable, task: Any, shared: Any) -> Any:
    return fn(task, shared)


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
    if scheduler:
        return _run_dask(fn, tasks, shared, scheduler, retries, done)
    import os

    workers = workers or os.cpu_count() or 1
    if workers == 1:
        out = {}
        for key, task in tasks.items():
            out[key] = _attempt_here(fn, key, task, shared, retries)
            done(out[key])
        return out
    return _run_pool(fn, tasks, shared, workers, retries, done)


def _attempt_here(fn, key, task, shared, retries) -> TaskOutcome:
    for attempt in range(1, retries + 2):
        try:
            return TaskOutcome(key, fn(task, shared), None, attempt)
        except Exception:  # noqa: BLE001 - reported per task
            error = traceback.format_exc(limit=3).strip().splitlines()[-1]
    return TaskOutcome(key, None, error, retries + 1)


def _run_pool(fn, tasks, shared, workers, retries, done) -> dict[str, TaskOutcome]:
    out: dict[str, TaskOutcome] = {}
    attempts = dict.fromkeys(tasks, 0)
    pending = list(tasks)
    while pending:
        pool = ProcessPoolExecutor(max_workers=workers)
        futures = {}
        for key in pending:
            attempts[key] += 1
            futures[pool.submit(_call, fn, tasks[key], shared)] = key
        pending = []
        broken = False
        while futures:
            finished, _ = wait(futures, return_when=FIRST_COMPLETED)
            for fut in finished:
                key = futures.pop(fut)
                try:
                    outcome = TaskOutcome(key, fut.result(), None, attempts[key])
                except BrokenProcessPool:
                    broken = True  # a worker process died: run its task again
                    outcome = None
                except Exception as exc:  # noqa: BLE001 - reported per task
                    outcome = TaskOutcome(key, None, f"{type(exc).__name__}: {exc}",
                                          attempts[key])
                if outcome is None or (not outcome.ok and attempts[key] <= retries):
                    if attempts[key] <= retries:
                        pending.append(key)
                        continue
                    outcome = outcome or TaskOutcome(
                        key, None, "the worker process died (every attempt)", attempts[key])
                out[key] = outcome
                done(outcome)
            if broken:  # the pool is unusable: collect what is left and start a new one
                for fut, key in futures.items():
                    if fut.done() and not fut.exception():
                        out[key] = TaskOutcome(key, fut.result(), None, attempts[key])
                        done(out[key])
                    else:
                        pending.append(key)
                futures = {}
        pool.shutdown(wait=True, cancel_futures=True)
    return out


def _run_dask(fn, tasks, shared, scheduler, retries, done) -> dict[str, TaskOutcome]:
    try:
        from distributed import Client, as_completed
    except ImportError:  # pragma: no cover - the dask extra is not installed
        raise RuntimeError("--scheduler needs Dask: pip install 'spm_sysid[dask]' "
                           "(dask and distributed)") from None
    out: dict[str, TaskOutcome] = {}
    with Client(scheduler, timeout=30) as client:
        shared_f = client.scatter(shared, broadcast=True) if shared is not None else None
        keys = list(tasks)
        futures = client.map(_call, [fn] * len(keys), [tasks[k] for k in keys],
                             [shared_f] * len(keys), key=[f"spm-sysid-{k}" for k in keys],
                             retries=retries, pure=False)
        by_future = dict(zip(futures, keys))
        for fut in as_completed(futures):
            key = by_future[fut]
            if fut.status == "finished":
                outcome = TaskOutcome(key, fut.result(), None, 1)
            else:
                exc = fut.exception()
                outcome = TaskOutcome(key, None, f"{type(exc).__name__}: {exc}", retries + 1)
            out[key] = outcome
            done(outcome)
    return out

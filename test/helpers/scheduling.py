"""A worker that crashes ends as one failed test, never as a suite that hangs.

pytest-xdist 3.8's group scheduling (``--dist loadgroup``, which ``make test``
uses to keep the Dask and colcon modules on one worker) deadlocks after a
worker crash: the dead worker's finished groups go back on the queue, are sent
again as empty units that never complete, and the run waits until CI's limit
(pytest-xdist issues 1323, 1327 and 1378; the fixes are merged there but not
released). A segmentation fault in one test then cost a 90-minute timeout and
no summary.

This scheduler is xdist's own with three mends:

- only groups that still hold tests go back on the queue, and an empty unit is
  never sent;
- a worker is told to finish as soon as the queue is empty, so a replacement
  given one test does not wait for a second;
- the test the worker died on is run once more, on a fresh worker
  (:func:`pytest_handlecrashitem`): a crash that comes back is a failure; one
  that does not is counted ("1 rerun" in the last line) and named in the
  summary, never passed over in silence.
"""

from __future__ import annotations

import pytest
from xdist.scheduler import LoadGroupScheduling


class CrashSafeGroupScheduling(LoadGroupScheduling):
    """``--dist loadgroup`` that survives a worker's crash."""

    def remove_node(self, node):
        workload = self.assigned_work.pop(node)
        pending = [nodeid for unit in workload.values()
                   for nodeid, done in unit.items() if not done]
        if not pending:
            return None
        crashed = pending[0]
        for unit in workload.values():
            if crashed in unit:
                unit[crashed] = True  # run again, if at all, by mark_test_pending
        for scope, unit in workload.items():
            if not all(unit.values()):
                self.workqueue[scope] = unit
        for other in self.nodes:
            self._reschedule(other)
        return crashed

    def mark_test_pending(self, item):
        """Queue a test that crashed its worker once more (its group's unit if queued)."""
        scope = self._split_scope(item)
        self.workqueue.setdefault(scope, {})[item] = False
        self.workqueue.move_to_end(scope, last=False)
        for node in self.nodes:
            self._reschedule(node)

    def _assign_work_unit(self, node):
        while self.workqueue:
            scope, unit = self.workqueue.popitem(last=False)
            indexes = [self.registered_collections[node].index(nodeid)
                       for nodeid, done in unit.items() if not done]
            if indexes:
                self.assigned_work.setdefault(node, {})[scope] = unit
                node.send_runtest_some(indexes)
                return

    def _reschedule(self, node):
        # a replacement worker still collecting gets its work once its collection is in
        # (worker_collectionfinish schedules every node again); before, a reschedule of
        # all nodes after another worker's crash asked for its collection: KeyError
        if node.shutting_down or node not in self.registered_collections:
            return
        while self.workqueue and self._pending_of(self.assigned_work[node]) <= 2:
            self._assign_work_unit(node)
        if not self.workqueue:
            node.shutdown()


#: Crashes seen in this session: (worker, test), in order.
CRASHES: list[tuple[str, str]] = []


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    """A test's first crash: run it again on a fresh worker, reported as a rerun."""
    if not isinstance(sched, CrashSafeGroupScheduling):
        return
    first = all(test != crashitem for _, test in CRASHES)
    CRASHES.append((report.node.gateway.id, crashitem))
    if first and _a_worker_replaces(sched.config):
        sched.mark_test_pending(crashitem)
        report.outcome = "rerun"


def _a_worker_replaces(config) -> bool:
    """Whether xdist starts a worker for the crashed one (past ``--max-worker-restart``
    it stops: a test queued again would never run, and its rerun would hide a failure)."""
    session = config.pluginmanager.getplugin("dsession")
    limit = getattr(session, "_max_worker_restart", 0)
    return limit is None or getattr(session, "_failed_nodes_count", limit) + 1 <= limit


def pytest_report_teststatus(report):
    if report.outcome == "rerun":
        return "rerun", "R", ("RERUN", {"yellow": True})
    return None


def pytest_terminal_summary(terminalreporter):
    """Every crash of a worker, and what became of its test."""
    if not CRASHES:
        return
    terminalreporter.section("workers that crashed", sep="-", yellow=True, bold=True)
    for worker, test in CRASHES:
        terminalreporter.line(f"worker {worker} crashed while running {test}")
    terminalreporter.line("a test whose worker crashed once runs again on a fresh worker; "
                          "a second crash is its failure")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """Group scheduling, crash-safe; any other ``--dist`` is xdist's own."""
    if config.getvalue("dist") == "loadgroup":
        return CrashSafeGroupScheduling(config, log)
    return None

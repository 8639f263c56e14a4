"""A test that takes its worker down fails alone: the suite goes on and ends.

``make test`` runs ``pytest -n 3 --dist loadgroup``; with pytest-xdist 3.8 a worker's
crash (a segmentation fault) made such a run wait forever after the crash (CI stopped
it at its limit, with no summary). test/helpers/scheduling.py mends the scheduler;
this runs a real xdist session over a small suite that crashes one worker.
"""

import os
import subprocess
import sys
import textwrap

import pytest

from .conftest import ROOT

#: real xdist sessions: a few seconds each (more on a busy machine)
pytestmark = pytest.mark.slow

QUICK = "import time\n\ndef test_quick():\n    time.sleep(0.05)\n"

GROUPED = """
import os
import pathlib
import signal

import pytest

pytestmark = pytest.mark.xdist_group("{group}")


def test_before():
    pass


def test_{name}():
    mark = pathlib.Path(__file__).with_name("{name}.crashed")
    if {always} or not mark.exists():
        mark.touch()
        os.kill(os.getpid(), signal.SIGSEGV)


def test_after():
    pass
"""


def test_a_crash_that_comes_back_fails_one_test_one_that_does_not_is_a_rerun_and_the_run_ends(
        tmp_path):
    # many finished modules on the worker that dies (they went back on the queue as
    # empty units and the run never ended), and a group with a test that crashes its
    # worker each time it runs and one that crashes it only the first time
    for i in range(20):
        (tmp_path / f"test_quick_{i:02d}.py").write_text(QUICK)
    (tmp_path / "test_g1.py").write_text(textwrap.dedent(
        GROUPED.format(group="g", name="always", always=True)))
    (tmp_path / "test_g2.py").write_text(textwrap.dedent(
        GROUPED.format(group="g", name="once", always=False)))
    run, out = _session(tmp_path)
    assert run.returncode == 1, out
    # each crashed once, ran again on a fresh worker; the one that crashed again failed
    assert "1 failed, 25 passed, 2 rerun" in out, out
    assert "FAILED test_g1.py::test_always - worker" in out, out
    summary = out[out.index("workers that crashed"):]
    for test, times in (("test_g1.py::test_always", 2), ("test_g2.py::test_once", 1)):
        assert summary.count(f"crashed while running {test}") == times, out



def test_a_crash_when_no_worker_may_replace_the_crashed_one_is_a_failure(tmp_path):
    # past --max-worker-restart no worker would run it again: counted as a rerun, the
    # test would end without a result and the run would pass
    (tmp_path / "test_g.py").write_text(textwrap.dedent(
        GROUPED.format(group="g", name="once", always=False)))
    run, out = _session(tmp_path, "--max-worker-restart", "0")
    assert run.returncode == 1, out
    last = run.stdout.strip().splitlines()[-1]
    assert "1 failed, 2 passed" in last and "rerun" not in last, out


def _session(folder, *options):
    """A real xdist session (two workers, groups, this project's scheduler) over folder."""
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadgroup", *options,
         "-p", "no:cacheprovider", "-p", "test.helpers.scheduling", str(folder)],
        cwd=folder, capture_output=True, text=True, timeout=240,
        env={**{k: v for k, v in os.environ.items() if not k.startswith("PYTEST")},
             "PYTHONPATH": str(ROOT)})
    return run, run.stdout + run.stderr


def test_a_replacement_worker_still_collecting_is_given_work_only_once_it_has_collected():
    """A reschedule of every node (after a crash) must pass over a worker still collecting.

    Seen in a loaded CI run: a crash's reschedule reached the crashed worker's
    replacement before its collection was in, and the session ended with an
    INTERNALERROR (KeyError in the scheduler).
    """
    from collections import OrderedDict

    from .helpers.scheduling import CrashSafeGroupScheduling

    class Worker:
        def __init__(self):
            self.shutting_down, self.sent = False, []

        def send_runtest_some(self, indexes):
            self.sent.append(indexes)

        def shutdown(self):
            self.shutting_down = True

    tests = ["test_a.py::test_one", "test_a.py::test_two"]
    sched = CrashSafeGroupScheduling.__new__(CrashSafeGroupScheduling)  # no xdist session
    sched.collection, sched.log = list(tests), lambda *args: None
    collected, collecting = Worker(), Worker()
    sched.assigned_work = {collected: {}, collecting: {}}
    sched.registered_collections = {collected: list(tests)}
    sched.workqueue = OrderedDict()
    sched.mark_test_pending(tests[1])  # what a crash's rerun does: every node rescheduled
    assert collecting.sent == [] and not collecting.shutting_down
    assert collected.sent == [[1]]
    sched.registered_collections[collecting] = list(tests)
    sched._reschedule(collecting)  # its collection in: nothing left, so it is told to end
    assert collecting.shutting_down

"""The node's parts that stand on their own, without a node or DDS (ros/futures.py,
ros/common.py, ros/node/identification.py's codes, ros/worker.py's errors)."""

import threading

import pytest

pytest.importorskip("rclpy", reason="the node's parts ship with the ROS layer")

from spm_sysid.core.errors import (  # noqa: E402
    BagError,
    DataError,
    MemoryLimitError,
    SettingsError,
    TooFewSamplesError,
)
from spm_sysid.ros.common import LOGGED_CALLBACK_ERRORS, CallbackErrors  # noqa: E402
from spm_sysid.ros.futures import Pending  # noqa: E402
from spm_sysid.ros.worker import JobError  # noqa: E402


def _job_error(exc: BaseException) -> JobError:
    """The error as the worker process reports it: its class names, nearest first."""
    return JobError(str(exc), tuple(c.__name__ for c in type(exc).__mro__))


def test_an_error_maps_to_its_code_by_its_class_and_its_bases():
    from spm_sysid.ros.node.identification import Code, code_of

    class NewDataError(DataError):  # a subclass nobody listed
        pass

    assert code_of(_job_error(TooFewSamplesError("few"))) == Code.TOO_FEW_SAMPLES
    assert code_of(_job_error(BagError("bag"))) == Code.BAD_DATA
    assert code_of(_job_error(NewDataError("new"))) == Code.BAD_DATA  # was FAILED
    assert code_of(_job_error(MemoryLimitError("big"))) == Code.INVALID_SETTINGS  # was FAILED
    assert code_of(_job_error(SettingsError("bad"))) == Code.INVALID_SETTINGS
    assert code_of(_job_error(RuntimeError("boom"))) == Code.FAILED
    assert JobError("x", "DataError").kind == "DataError"  # one name still reads


def _settled(make):
    """The future of ``make(wake)`` once its wake-up came (as the executor would be woken)."""
    woken = threading.Event()
    pending = make(woken.set)
    assert woken.wait(60)
    return pending.future


def test_pending_is_settled_once_from_any_thread_and_wakes_the_executor():
    woken = []
    pending = Pending(lambda: woken.append(True))
    threads = [threading.Thread(target=pending.settle, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert pending.future.done() and pending.future.result() in range(8)
    assert woken == [True]  # the first settlement only
    ran = _settled(lambda wake: Pending.run(lambda: 42, wake))
    assert ran.result() == 42
    timed = _settled(lambda wake: Pending.run(threading.Event().wait, wake, timeout=0.05,
                                              on_timeout=lambda: OSError("too slow")))
    with pytest.raises(OSError, match="too slow"):
        timed.result()


def test_callback_errors_are_counted_and_only_the_first_ones_logged():
    class Log:
        def __init__(self):
            self.lines = []

        def error(self, text):
            self.lines.append(text)

    log = Log()
    errors = CallbackErrors(log)
    for i in range(LOGGED_CALLBACK_ERRORS + 5):
        try:
            raise ValueError(f"bad {i}")
        except ValueError as exc:
            errors(exc)
    assert errors.count == LOGGED_CALLBACK_ERRORS + 5
    assert len(log.lines) == LOGGED_CALLBACK_ERRORS
    assert "a callback raised ValueError: bad 0" in log.lines[0]

"""Job functions for the worker tests (imported by the worker process)."""

import time


def sleepy(seconds: float, progress=None) -> float:
    """Sleep, then return the seconds: a job that runs as long as the test wants."""
    time.sleep(seconds)
    return seconds

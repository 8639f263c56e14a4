"""One BLAS thread while the core computes.

The core's matrices are small (rows x tens of terms: QR fits of one structure,
triangular solves, Jacobians of a refinement), where OpenBLAS's threads cost
more to wake and synchronise than they save -- much more when another process
keeps a core busy. Measured on the robot-arm data, simulation focus: 3.2-3.9 s
with OpenBLAS's default (two threads on two cores), 2.1 s with one. The
parallel parts (certification heaps, outputs of a coupled model, Dask
workers) run on threads or processes of their own. The limit holds only while
a job runs (``threadpoolctl``), so a caller's own numpy work keeps its threads.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["one_blas_thread"]


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Limit BLAS to one thread inside the block (also a decorator)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield

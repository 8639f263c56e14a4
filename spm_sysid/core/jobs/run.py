"""The job of any record: one output or several, one entry for every caller.

The command line, ``batch``, the node's worker process, the ``make run``
pipeline and the benchmarks all call :func:`run_job`. A record of one output
runs :func:`~spm_sysid.core.jobs.single.run_single_job`; of several outputs,
:func:`~spm_sysid.core.jobs.several.run_mimo_job` (one coupled model).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..blas import one_blas_thread
from ..model.narx import NarxModel
from ..model.terms import TermSpace
from ..progress import ProgressFn
from ..record import Record
from .settings import JobSettings
from .several import MimoJobResult, run_mimo_job
from .single import JobResult, run_single_job

__all__ = ["run_job", "warm_up"]


def warm_up() -> None:
    """Load (or, the first time, compile) the compiled kernels every job runs, once.

    The node's worker process calls it before it reports ready, so the time of a
    job (and its ``job_timeout``) is the job's own. The refinement's kernels
    (simulation focus) are not among them: where ``spm-sysid compile`` has not
    cached them (a colcon install tree), compiling them takes about 30 s, which
    the first job that refines pays once, not every start of the node.
    """
    from ..fit.evaluator import StructureEvaluator

    StructureEvaluator(np.eye(3), np.ones(3)).evaluate(np.eye(3, dtype=bool))
    model = NarxModel(TermSpace(ny=1, nu=1, degree=1), [0, 1], np.array([0.5, 0.1]))
    model.run(np.zeros(6), np.ones(6), horizon=2)


@one_blas_thread()
def run_job(record: Record, settings: JobSettings, *, progress: ProgressFn | None = None,
            progress_every: int = 25, metadata: Mapping[str, Any] | None = None
            ) -> JobResult | MimoJobResult:
    """Identify and validate a record: one model, or one coupled model of several outputs.

    Parameters, result and errors: :func:`~spm_sysid.core.jobs.single.run_single_job`
    (one output) and :func:`~spm_sysid.core.jobs.several.run_mimo_job` (several).
    With ``spikes`` ``gaps`` the output's spikes become gaps first
    (:meth:`~spm_sysid.core.record.Record.spikes_as_gaps`); with ``decimate``
    above 1 the record is decimated then
    (:meth:`~spm_sysid.core.record.Record.decimated`): the job, its model and its
    validation are at the slower rate.
    """
    period = int(round(settings.sample_period * 1e9)) or None
    if settings.spikes == "gaps":  # at the record's rate
        record = record.spikes_as_gaps(period, settings.gap_factor)
    if settings.decimate > 1:  # the job runs at the slower rate, the document says so
        record = record.decimated(settings.decimate, period, settings.gap_factor)
    if record.n_outputs > 1:  # one coupled model of several outputs
        return run_mimo_job(record, settings, progress=progress,
                            progress_every=progress_every, metadata=metadata)
    return run_single_job(record, settings, progress=progress, progress_every=progress_every,
                          metadata=metadata)

"""Jobs: a record and settings in, a validated model out (one output or several)."""

from .run import run_job, warm_up
from .settings import JobSettings
from .several import MimoJobResult, run_mimo_job
from .single import JobResult, describe_selection, run_single_job, validation_segments

__all__ = ["JobResult", "JobSettings", "MimoJobResult", "describe_selection", "run_job",
           "run_mimo_job", "run_single_job", "validation_segments", "warm_up"]

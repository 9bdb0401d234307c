"""The fusion-machine job: load crucibles, run the fusion, unload glass beads, lose nothing.

:mod:`~fxcell.job.spec` (the run and its validation), :mod:`~fxcell.job.plan` (its steps),
:mod:`~fxcell.job.store` (the SQLite record of locations and steps), :mod:`~fxcell.job.runner`
(the :class:`Job` and the :class:`JobCell` interface it drives).
"""

from fxcell.job.plan import Step, final_locations, initial_locations, make_plan
from fxcell.job.runner import Job, JobCell, JobIO, Question
from fxcell.job.spec import Run, RunSpec, Sample, SampleSpec, load_run, validate_run
from fxcell.job.store import JobStore

__all__ = [
    "Job",
    "JobCell",
    "JobIO",
    "JobStore",
    "Question",
    "Run",
    "RunSpec",
    "Sample",
    "SampleSpec",
    "Step",
    "final_locations",
    "initial_locations",
    "load_run",
    "make_plan",
    "validate_run",
]

"""``licalib batch``: calibrate a fleet's bags on Dask, locally or on a cluster, resumably.

Inputs (:mod:`.inputs`) become jobs; :mod:`.plan` finds what earlier runs already did;
:mod:`.run` submits one task (:mod:`.task`) per remaining bag to the cluster of :mod:`.cluster`,
writes each result as it finishes and the fleet summary of :mod:`.summary`.
"""

from __future__ import annotations

from licalib_cli.batch.inputs import COLUMNS, BatchJob, read_inputs
from licalib_cli.batch.plan import PlannedBag, plan
from licalib_cli.batch.run import BatchReport, run_batch
from licalib_cli.batch.summary import BagRow, RigRow, compare_within_rig
from licalib_cli.batch.task import TaskInput, TaskOutcome, calibrate_task

__all__ = [
    "COLUMNS",
    "BagRow",
    "BatchJob",
    "BatchReport",
    "PlannedBag",
    "RigRow",
    "TaskInput",
    "TaskOutcome",
    "calibrate_task",
    "compare_within_rig",
    "plan",
    "read_inputs",
    "run_batch",
]

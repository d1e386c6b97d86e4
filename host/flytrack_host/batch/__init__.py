"""Batches of offline work (re-tracking, parameter sweeps, exports) on Dask.

`plan` turns recordings and parameter sets into tasks with fixed output paths, `tasks` runs one task
on a worker (atomic output, so a task killed half-way leaves nothing that looks finished), `runner`
submits them to a dask.distributed cluster (a LocalCluster by default, or any scheduler by address)
with a progress bar, `results` writes the table (CSV and Parquet) and `plot` compares parameter sets.

May import: util, geometry, recording, io.
"""

from flytrack_host.batch.plan import BatchError, ParamSet, Task, param_sets, plan_exports, plan_retracks
from flytrack_host.batch.runner import BatchReport, run_batch

__all__ = ["BatchError", "BatchReport", "ParamSet", "Task", "param_sets", "plan_exports", "plan_retracks",
           "run_batch"]

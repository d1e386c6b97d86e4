"""Run batch tasks on a dask.distributed cluster: a LocalCluster by default, any cluster by address.

Tasks carry paths, not data: workers read the recordings where they lie, and only each task's small
result row travels back through the scheduler. Finished outputs are skipped before anything is
submitted (resumable); a task that fails is reported with its error and the others go on; a task
whose worker dies is re-run by the scheduler on another worker, and its atomic output (tasks.py)
means it is never counted or written twice.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from flytrack_host.batch.plan import BatchError, Task
from flytrack_host.batch.tasks import FAILED_KEY, finished_row, run_task, run_task_on_worker


@dataclass
class BatchReport:
    rows: list[dict[str, Any]] = field(default_factory=list)  # one per finished task, skipped ones too
    skipped: int = 0  # finished before this run
    ran: int = 0
    failures: list[tuple[str, str]] = field(default_factory=list)  # (task label, error)
    wall_s: float = 0.0
    startup_s: float = 0.0  # of wall_s: starting the local cluster or connecting to the scheduler
    workers: int = 0
    scheduler: str = ""


def _client(scheduler: str | None, workers: int | None) -> tuple[Any, Any]:
    # dask is imported here so that `flytrack --help` and the serial path do not pay for it.
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError) as exc:
            raise BatchError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    n = workers or os.cpu_count() or 1
    # One thread per worker process: the tracker is single-threaded NumPy/C, and processes avoid the GIL.
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR)
    return Client(cluster), cluster


def _clean_partials(tasks: list[Task]) -> None:
    """Remove `.partial-*` folders left by workers that died before they renamed their output."""
    for parent in {t.out.parent for t in tasks}:
        if parent.is_dir():
            for p in parent.glob("*.partial-*"):
                shutil.rmtree(p, ignore_errors=True)


def run_batch(tasks: list[Task], scheduler: str | None = None, workers: int | None = None,
              progress: bool = True, serial: bool = False) -> BatchReport:
    """Run `tasks`; `serial=True` runs them one after another in this process (no Dask)."""
    rep = BatchReport()
    todo = []
    for t in tasks:
        row = finished_row(t)
        if row is None:
            todo.append(t)
        else:
            rep.rows.append(row)
            rep.skipped += 1
    t0 = time.monotonic()
    bar = tqdm(total=len(todo), disable=not progress or not todo, unit="task", desc="batch")
    if serial:
        rep.scheduler, rep.workers = "serial (this process)", 1
        for t in todo:
            try:
                rep.rows.append(run_task(t))
                rep.ran += 1
            except Exception as exc:  # one failed task is reported; the rest go on
                rep.failures.append((t.label, f"{type(exc).__name__}: {exc}"))
            bar.update()
    elif todo:
        from dask.distributed import as_completed

        t_start = time.monotonic()
        client, cluster = _client(scheduler, workers)
        rep.startup_s = time.monotonic() - t_start
        try:
            rep.scheduler = client.scheduler.address
            rep.workers = len(client.scheduler_info(n_workers=-1)["workers"])
            futures = {client.submit(run_task_on_worker, t, key=t.key, pure=False): t for t in todo}
            for fut in as_completed(futures):
                t = futures[fut]
                if fut.status == "finished":
                    row = fut.result()
                    if FAILED_KEY in row:
                        rep.failures.append((t.label, str(row[FAILED_KEY])))
                    else:
                        rep.rows.append(row)
                        rep.ran += 1
                else:
                    exc = fut.exception()
                    rep.failures.append((t.label, f"{type(exc).__name__}: {exc}"))
                bar.update()
                fut.release()
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    bar.close()
    rep.wall_s = time.monotonic() - t0
    _clean_partials(tasks)
    return rep

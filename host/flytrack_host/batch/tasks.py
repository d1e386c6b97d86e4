"""One batch task, run on a Dask worker: re-track or export one recording into its fixed output.

A task reads its input where it lies (a path every worker can see) and writes its output under a
temporary name beside the final one, renamed into place only when complete, with the task's result
row inside (`batch_result.json`). So a worker killed half-way leaves at most a `.partial-*` folder,
never an output that looks finished; a task run twice (a worker lost after the rename, before it
reported) finds the output and returns its row instead of producing a second one.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import uuid
from pathlib import Path
from typing import Any

from flytrack_host.batch.metrics import recording_metrics
from flytrack_host.batch.plan import Task, source_stem

RESULT_NAME = "batch_result.json"


def finished_row(task: Task) -> dict[str, Any] | None:
    """The result row of a task whose output is complete, else None."""
    p = task.out / RESULT_NAME
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None  # unreadable: run it again (the rename below refuses to clobber, so nothing is lost)


def run_task(task: Task) -> dict[str, Any]:
    """Do one task; returns its result row. Exceptions propagate (the runner reports them per task)."""
    done = finished_row(task)
    if done is not None:
        return done
    task.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = task.out.with_name(f"{task.out.name}.partial-{uuid.uuid4().hex[:8]}")
    try:
        row = _retrack(task, tmp) if task.kind == "retrack" else _export(task, tmp)
        row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
        (tmp / RESULT_NAME).write_text(json.dumps(row, indent=1), encoding="utf-8")
        try:
            os.rename(tmp, task.out)  # atomic on one filesystem; fails if the output appeared meanwhile
        except OSError:
            other = finished_row(task)
            if other is None:
                raise
            return other  # another run of the same task finished first: keep its output, drop ours
        return row
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


FAILED_KEY = "_failed"


def run_task_on_worker(task: Task) -> dict[str, Any]:
    """run_task for a Dask worker: a task that fails returns {FAILED_KEY: "Type: message"} instead of
    raising, so the worker does not log a traceback per bad recording; the runner lists it as failed."""
    try:
        return run_task(task)
    except Exception as exc:  # reported per task by the runner; the worker and the other tasks go on
        return {FAILED_KEY: f"{type(exc).__name__}: {exc}"}


def _base_row(task: Task) -> dict[str, Any]:
    return {"recording": str(task.source), "name": source_stem(task.source), "params": task.params.name,
            "overrides": json.dumps(task.params.overrides), "output": str(task.out)}


def _retrack(task: Task, tmp: Path) -> dict[str, Any]:
    from flytrack_host.io.retrack import RetrackError, cameras_for, load_2d, params_with, retrack

    data = load_2d(task.source, stream=True)  # a recording in parts: re-tracked part by part
    cams = cameras_for(data, task.calibration)
    params = params_with(data.tracking_params, None, list(task.params.sets))
    fps = task.fps or data.fps
    if not fps:
        raise RetrackError(f"{task.source}: the source does not give the frame rate: pass --fps")
    res = retrack(data, cams, params, fps, out=tmp, progress=False)
    row = _base_row(task)
    row.update(recording_metrics(tmp, cams))
    if res.why_nothing:  # why it tracked nothing although 2D points came (retrack's reasons, with numbers)
        row["why_no_estimates"] = "; ".join(res.why_nothing)
    row.update({"frames": res.frames, "tracker_s": res.seconds,
                "frames_per_s": res.frames / res.seconds if res.seconds > 0 else float("nan")})
    return row


def _export(task: Task, tmp: Path) -> dict[str, Any]:
    from flytrack_host.io.braidz import export_braidz
    from flytrack_host.io.csv_export import export_csv
    from flytrack_host.recording.source import open_source

    rec = open_source(task.source)  # a recording in parts is exported part by part
    tmp.mkdir(parents=True)
    row = _base_row(task)
    if "braidz" in task.formats:
        counts = export_braidz(rec, tmp / f"{task.out.name}.braidz")
        row["braidz_rows"] = json.dumps(counts)
    if "csv" in task.formats:
        row["csv_files"] = len(export_csv(rec, tmp / "csv"))
    return row

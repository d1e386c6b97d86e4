"""A Python function called for each firing (custom stimulus code), in the output's worker thread.

`address = "package.module:function"` or `"path/to/file.py:function"` (relative to the rig file).
The function gets `firing` (a dict: rule, obj_id, condition_frame, scheduled_frame, x, y, z) and the
action's `params` as keyword arguments; `time_ack` is when it returned. An exception is a failed
action (logged, counted), never a stopped run.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock


def load_hook(address: str, base_dir: Path | None = None) -> Callable[..., Any]:
    target, sep, func = address.rpartition(":")
    if not sep or not target or not func:
        raise OutputError(f"{address!r} is not module:function or file.py:function")
    if target.endswith(".py"):
        path = Path(target)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if not path.exists():
            raise OutputError(f"hook file {path} does not exist")
        spec = importlib.util.spec_from_file_location(f"flytrack_hook_{path.stem}", path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    else:
        try:
            mod = importlib.import_module(target)
        except ImportError as exc:
            raise OutputError(f"cannot import {target}: {exc}") from None
    fn = getattr(mod, func, None)
    if not callable(fn):
        raise OutputError(f"{address}: no function {func!r}")
    return fn


class PythonHookOutput(Output):
    kind = "python"
    ack_means = "the function returned"

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.fn: Callable[..., Any] | None = None

    def _connect(self) -> None:
        self.fn = load_hook(self.cfg.address, self.context.get("base_dir"))

    def _perform(self, job: Job) -> Done:
        assert self.fn is not None
        x, y, z = job.pos
        firing = {"rule": job.rule, "obj_id": job.obj_id, "condition_frame": job.condition_frame,
                  "scheduled_frame": job.scheduled_frame, "x": x, "y": y, "z": z}
        t0 = hostclock.now()
        self.written()  # custom code may take long: the tracking thread does not wait for it
        self.fn(firing, **job.action.params)
        return Done(t0, hostclock.now())

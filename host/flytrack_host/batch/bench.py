"""`make bench-batch`: a batch of 8 re-tracking tasks, serially in one process and on a local Dask
cluster of 2 single-threaded worker processes, in the same run, with the speed-up.

The serial run is what a user would otherwise do (a loop of `flytrack retrack`, without paying for a
process start per recording): the same task function, in-process. The Dask run includes starting the
cluster, as a user's command does.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from flytrack_host.batch import param_sets, plan_retracks, run_batch
from flytrack_host.recording.synthetic import write_synthetic_recording


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recordings", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=60.0, help="length of each synthetic recording (a lab's are "
                    "minutes to hours; per-task overheads weigh more on short ones)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="flytrack-bench-batch-") as d:
        root = Path(d)
        t0 = time.monotonic()
        recs = [write_synthetic_recording(root / "in" / f"rec{i}.flytrack", n_cameras=5, n_targets=3,
                                          duration_s=a.seconds, seed=i).parent for i in range(a.recordings)]
        print(f"made {len(recs)} synthetic recordings (5 cameras, 3 animals, {a.seconds:g} s at 100 fps) "
              f"in {time.monotonic() - t0:.1f} s")
        figures = {}
        for mode in ("serial", "dask"):
            out = root / mode
            tasks = plan_retracks(recs, param_sets(), out)
            rep = run_batch(tasks, workers=a.workers, progress=False, serial=(mode == "serial"))
            assert not rep.failures and rep.ran == len(tasks), rep.failures
            figures[mode] = rep.wall_s
            frames = sum(r["frames"] for r in rep.rows)
            figures[f"{mode}_startup"] = rep.startup_s
            print(f"{mode:>6}: {rep.wall_s:6.2f} s wall for {len(tasks)} recordings ({frames} frames) "
                  f"on {rep.workers} worker{'s' if rep.workers > 1 else ''}"
                  + (f", of which {rep.startup_s:.2f} s starting the cluster" if mode == "dask" else ""))
            shutil.rmtree(out)
        speedup = figures["serial"] / figures["dask"]
        print(f"speed-up on {a.workers} Dask workers: {speedup:.2f}x (ideal {a.workers}x; the Dask figure "
              f"includes starting the local cluster)")
    if a.json:
        fig = {"recordings": a.recordings, "seconds_each": a.seconds, "workers": a.workers,
               "serial_wall_s": figures["serial"], "dask_wall_s": figures["dask"],
               "dask_startup_s": figures["dask_startup"], "speedup": speedup}
        a.json.write_text(json.dumps({"batch": fig}, indent=1))

if __name__ == "__main__":
    main()

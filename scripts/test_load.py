#!/usr/bin/env python3
"""Run the whole test suite under a background CPU load, several times, and print the failures per run.

A lab's PC is busy: a test that passes only on an idle machine is waiting for a time instead of a
condition, or judging against a figure the idle machine happened to give. stress-ng keeps twice as
many CPU hogs as there are cores running for the whole of each run.

    scripts/test_load.py                 # 3 runs, load 2 x cores
    scripts/test_load.py --runs 1 --load 4 -- host/tests/host   # extra arguments go to pytest

Exit status 0 only when every run passed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_portability import ROOT, run_pytest  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--load", type=int, default=2 * (os.cpu_count() or 1),
                    help="stress-ng CPU workers (default: twice the cores)")
    ap.add_argument("--log-dir", type=Path, default=ROOT / "build" / "load")
    ap.add_argument("pytest_args", nargs="*", help="arguments for pytest (default: the whole suite)")
    a = ap.parse_args()
    if shutil.which("stress-ng") is None:
        print("test-load: stress-ng is not installed (Debian package stress-ng; `make test-load` installs it)",
              file=sys.stderr)
        return 2
    a.log_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for i in range(1, a.runs + 1):
        print(f"run {i}/{a.runs}: the suite under stress-ng --cpu {a.load} ...", flush=True)
        # Its own process group, so the hogs end with it whatever happens to this script.
        # --timeout: a backstop should this script be killed before it can stop them.
        hog = subprocess.Popen(["stress-ng", "--cpu", str(a.load), "--timeout", "7200", "--quiet"],
                               start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            r = run_pytest(a.pytest_args, {}, f"load-run{i}", a.log_dir)
        finally:
            os.killpg(hog.pid, signal.SIGTERM)
            hog.wait()
        results.append(r)
        print(f"  run {i}: {r['passed']} passed, {r['failed']} failed ({r['seconds']} s)", flush=True)
        for f in r["failures"]:
            print(f"    FAILED {f}", flush=True)
    print()
    print(f"{'run':<5} {'passed':>7} {'failed':>7} {'seconds':>8}")
    for i, r in enumerate(results, 1):
        print(f"{i:<5} {r['passed']:>7} {r['failed']:>7} {r['seconds']:>8}")
    ok = all(r["rc"] == 0 for r in results)
    print("test-load:", "every run passed" if ok else f"FAILURES above (logs in {a.log_dir})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

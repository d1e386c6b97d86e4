#!/usr/bin/env python3
"""Run the numerical tests under every OpenBLAS kernel this CPU can run, then the suite in random order.

A lab's PC has any CPU, any BLAS kernel and any thread count; a test whose property held only on the
kernel of the machine it was written on fails there. OpenBLAS picks its kernel at load time from the CPU
unless OPENBLAS_CORETYPE names one, so one machine can stand in for many.

    scripts/test_portability.py            # the table: core type x BLAS threads -> passed/failed,
                                           # then the whole suite once in random order (seed printed)
    scripts/test_portability.py --other    # the numerical tests once, under one core type that is
                                           # not this machine's own (what `make test` runs)
    scripts/test_portability.py --no-suite --core-types Haswell,Zen --threads 1

Exit status 0 only when every run passed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable

# The tests whose results come out of floating-point maths: tracking, calibration, refraction, fish,
# wing beats, the trigger clock model, the event algorithms.
NUMERICAL_TESTS = [
    "host/tests/tracking",
    "host/tests/calibration",
    "host/tests/geometry",
    "host/tests/fish",
    "host/tests/wingbeat",
    "host/tests/trigger/test_clock_model.py",
    "host/tests/events/test_algos.py",
    "host/tests/eventcam",
]

# OpenBLAS core types (its names for OPENBLAS_CORETYPE) and the CPU flags each kernel needs, oldest first.
# On x86_64 the flags are /proc/cpuinfo's; on aarch64 its "Features".
X86_CORE_TYPES: list[tuple[str, set[str]]] = [
    ("Prescott", {"pni"}),
    ("Nehalem", {"ssse3", "sse4_2"}),
    ("Sandybridge", {"avx"}),
    ("Haswell", {"avx2", "fma"}),
    ("Zen", {"avx2", "fma"}),
    ("SkylakeX", {"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl"}),
    ("Cooperlake", {"avx512_bf16"}),
]
ARM_CORE_TYPES: list[tuple[str, set[str]]] = [
    ("ARMV8", set()),
    ("CortexA57", set()),
    ("NeoverseN1", {"asimddp"}),
    ("NeoverseV1", {"sve"}),
]


def cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    m = re.search(r"^(?:flags|Features)\s*:\s*(.*)$", text, re.M)
    return set(m.group(1).split()) if m else set()


def runnable_core_types() -> list[str]:
    table = ARM_CORE_TYPES if platform.machine() in ("aarch64", "arm64") else X86_CORE_TYPES
    flags = cpu_flags()
    return [name for name, need in table if need <= flags]


def own_core_type() -> str:
    """The kernel the rest of the suite runs under: OPENBLAS_CORETYPE when the environment sets it (some
    machines do), else the one OpenBLAS picks for this CPU by itself (as threadpoolctl reports it)."""
    if os.environ.get("OPENBLAS_CORETYPE"):
        return os.environ["OPENBLAS_CORETYPE"]
    code = (
        "import numpy, threadpoolctl\n"
        "print(next((i.get('architecture') or '?' for i in threadpoolctl.threadpool_info()"
        " if i.get('internal_api') == 'openblas'), '?'))"
    )
    out = subprocess.run([PY, "-c", code], capture_output=True, text=True, check=False)
    return out.stdout.strip() or "?"


def run_pytest(args: list[str], env_extra: dict[str, str], label: str, log_dir: Path) -> dict:
    """One pytest run; returns its counts and the failing test ids (parsed from -rf's summary)."""
    env = dict(os.environ, **env_extra)
    log = log_dir / f"{label}.log"
    t0 = time.monotonic()
    with log.open("w") as fh:
        rc = subprocess.run([PY, "-m", "pytest", "-q", "-rf", *args], cwd=ROOT, env=env, stdout=fh,
                            stderr=subprocess.STDOUT, check=False).returncode
    text = log.read_text(errors="replace")
    counts = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|errors?|skipped)", text.splitlines()[-1]
                                                 if text else "")}
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", text, re.M)
    return {"label": label, "rc": rc, "passed": counts.get("passed", 0),
            "failed": counts.get("failed", 0) + counts.get("error", 0) + counts.get("errors", 0),
            "failures": failed, "seconds": round(time.monotonic() - t0, 1), "log": str(log)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--other", action="store_true",
                    help="run the numerical tests once, under one core type other than this machine's own")
    ap.add_argument("--core-types", help="comma-separated OpenBLAS core types (default: all this CPU runs)")
    ap.add_argument("--threads", default="1,2", help="BLAS thread counts to try (default 1,2)")
    ap.add_argument("--no-suite", action="store_true", help="skip the whole suite in random order")
    ap.add_argument("--json", type=Path, help="write the results here as JSON")
    ap.add_argument("--log-dir", type=Path, default=ROOT / "build" / "portability")
    a = ap.parse_args()
    a.log_dir.mkdir(parents=True, exist_ok=True)

    runnable = runnable_core_types()
    own = own_core_type()
    if not runnable:
        print("test-portability: this CPU runs none of the core types in the table", file=sys.stderr)
        return 2
    if a.other:
        # The oldest kernel this CPU runs that is not its own: the one furthest from what the suite sees.
        others = [c for c in runnable if c.lower() != own.lower()]
        core = others[0] if others else runnable[0]
        print(f"numerical tests under OPENBLAS_CORETYPE={core} (the suite's own: {own})", flush=True)
        env = {"OPENBLAS_CORETYPE": core, "OPENBLAS_NUM_THREADS": "1"}
        r = run_pytest(NUMERICAL_TESTS, env, f"numerical-{core}", a.log_dir)
        print(f"{core}: {r['passed']} passed, {r['failed']} failed in {r['seconds']} s")
        for f in r["failures"]:
            print(f"  FAILED {f}")
        if r["rc"] != 0:
            print(f"  log: {r['log']}")
        return r["rc"]

    cores = a.core_types.split(",") if a.core_types else runnable
    threads = [t.strip() for t in a.threads.split(",") if t.strip()]
    print(f"this CPU runs OpenBLAS core types: {', '.join(runnable)} (the suite's own: {own})")
    print(f"numerical tests: {' '.join(NUMERICAL_TESTS)}", flush=True)
    rows = []
    for core in cores:
        for t in threads:
            r = run_pytest(NUMERICAL_TESTS, {"OPENBLAS_CORETYPE": core, "OPENBLAS_NUM_THREADS": t},
                           f"numerical-{core}-{t}", a.log_dir)
            r.update(core=core, threads=t)
            rows.append(r)
            print(f"  {core:<12} {t} thread(s): {r['passed']} passed, {r['failed']} failed ({r['seconds']} s)",
                  flush=True)
    suite = None
    if not a.no_suite:
        seed = int.from_bytes(os.urandom(4), "little")
        print(f"whole suite in random order: pytest -p randomly --randomly-seed={seed} ...", flush=True)
        suite = run_pytest(["-p", "randomly", f"--randomly-seed={seed}"], {}, "suite-random", a.log_dir)
        suite["seed"] = str(seed)

    print()
    print(f"{'core type':<12} | " + " | ".join(f"{t} thread(s)" for t in threads))
    print("-" * 13 + "+" + "+".join("-" * 13 for _ in threads))
    for core in cores:
        cells = []
        for t in threads:
            r = next(x for x in rows if x["core"] == core and x["threads"] == t)
            cells.append(f"{r['passed']:>4} ok" + (f", {r['failed']} FAIL" if r["failed"] or r["rc"] else ""))
        print(f"{core:<12} | " + " | ".join(c.ljust(11) for c in cells))
    for r in rows:
        for f in r["failures"]:
            print(f"FAILED [{r['core']}, {r['threads']} thread(s)] {f}")
    ok = all(r["rc"] == 0 for r in rows)
    if suite is not None:
        print(f"whole suite, random order, --randomly-seed={suite['seed']}: {suite['passed']} passed, "
              f"{suite['failed']} failed ({suite['seconds']} s)")
        for f in suite["failures"]:
            print(f"FAILED [random order] {f}")
        ok = ok and suite["rc"] == 0
    if a.json:
        a.json.write_text(json.dumps({"own_core_type": own, "runs": rows, "suite": suite}, indent=1))
    print("test-portability:", "all passed" if ok else "FAILURES above (logs in " + str(a.log_dir) + ")")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

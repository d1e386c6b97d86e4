"""`make mutation`: mutation testing (mutmut 2.5.1) of the tracker, the synchroniser and the recorder.

Each module is mutated with mutmut in a scratch copy of the repository (mutmut edits files in place;
the working tree is never touched), and only that module's fast unit tests run against each mutant.
Prints, per module, the mutants killed / total and the share killed, and the goal (>= 85 % on ekf.py,
association.py, birth.py and the synchroniser, flytrack_host/intake/sync/). Slow (minutes per module on an
idle core): not part of `make test`. MUTATION_MODULES='ekf sync' restricts the run; MUTATION_JSON=PATH
writes the figures.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FORKSERVER = ROOT / "scripts" / "mutation_forkserver.py"
# module name -> (file to mutate, its fast tests); paths relative to the repository root.
MODULES: dict[str, tuple[str, list[str]]] = {
    "ekf": ("host/flytrack_host/tracking/ekf.py", ["host/tests/tracking/test_ekf.py"]),
    "association": ("host/flytrack_host/tracking/association.py", ["host/tests/tracking/test_association.py"]),
    "birth": ("host/flytrack_host/tracking/birth.py", ["host/tests/tracking/test_birth.py"]),
    # The synchroniser's fault cases in test_faults_units.py too (-k: the ones driving FrameSynchronizer);
    # not the 2-3 s random-stall soak, which every surviving mutant would pay for (a mutant only it
    # catches counts as surviving).
    # The synchroniser's code: every module of the flytrack_host.intake.sync package but its re-exports.
    "sync": (",".join(f"host/flytrack_host/intake/sync/{m}.py" for m in
                      ("synchronizer", "restart", "drift", "windows", "state", "clock", "types")),
             ["host/tests/host/test_sync_bundles.py", "host/tests/host/test_sync_rejected.py",
              "host/tests/host/test_sync_start.py", "host/tests/host/test_sync_jumps.py",
              "host/tests/host/test_sync_edge_restarts.py", "host/tests/host/test_sync_clock.py",
              "host/tests/host/test_sync_drift.py", "host/tests/host/test_sync_bursty.py",
              "host/tests/host/test_sync_behaviour_bundles.py", "host/tests/host/test_sync_behaviour_start.py",
              "host/tests/host/test_sync_behaviour_numbering.py", "host/tests/host/test_sync_behaviour_ahead.py",
              "host/tests/host/test_sync_behaviour_remap.py", "host/tests/host/test_sync_behaviour_clock.py",
              "host/tests/host/test_sync_behaviour_drift.py", "host/tests/host/test_sync_window.py",
              "host/tests/host/test_sync_mapping_edges.py",
              "host/tests/host/test_sync_restart.py", "host/tests/host/test_sync_restart_drift.py",
              "host/tests/host/test_faults_units.py", "-k",
              "'(not faults_units or wrong_numbers or gap_in_the_good or edge_restart or reanchored "
              "or stall_and_burst or restarted_edge) and not repeated_random_stalls'"]),
    # The recorder's writer (raw files, flushes, disk errors) and finalisation (raw files -> HDF5,
    # recovery), against its fast tests (not the 12-22 s SIGKILL and real-disk-full end-to-end runs).
    "recording": ("host/flytrack_host/recording/writer.py,host/flytrack_host/recording/finalize.py",
                  ["host/tests/host/test_finalize.py", "host/tests/host/test_recorder_faults.py",
                   "host/tests/host/test_recorder_contract.py"]),
}
GOAL = {"ekf": 0.85, "association": 0.85, "birth": 0.85, "sync": 0.85}


def _module_name(target: str) -> str:
    """host/flytrack_host/tracking/birth.py -> flytrack_host.tracking.birth (a folder: its package;
    several comma-separated files: their common package)."""
    if "," in target:
        parts = [Path(t).relative_to("host").parent.parts for t in target.split(",")]
        common = []
        for level in zip(*parts, strict=False):
            if len(set(level)) > 1:
                break
            common.append(level[0])
        return ".".join(common)
    rel = Path(target).relative_to("host")
    return ".".join(rel.with_suffix("").parts if rel.suffix == ".py" else rel.parts)


# mutmut_config.py of shard k of n: mutmut skips the mutants of the other shards (by queue index).
SHARD_CONFIG = """def pre_mutation(context):
    if context.index % {n} != {k}:
        context.skip = True
"""


def _prepare(work: Path) -> None:
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    for part in ("host", "pytest.ini", "ruff.toml"):
        src = ROOT / part
        if src.is_dir():
            shutil.copytree(src, work / part, ignore=shutil.ignore_patterns("__pycache__", ".hypothesis"))
        elif src.exists():
            shutil.copy2(src, work / part)


def _recheck(work: Path, target: str, runner: str, env: dict, py: str) -> None:
    """Run each surviving mutant of a finished run again (mutmut apply, the runner, restore)."""
    with sqlite3.connect(work / ".mutmut-cache") as db:
        ids = [i for (i,) in db.execute("SELECT id FROM Mutant WHERE status = 'bad_survived' ORDER BY id")]
        for i in ids:
            for t in target.split(","):  # the unmutated file(s) back before each mutant
                shutil.copy2(ROOT / t, work / t)
            ap = subprocess.run([py, "-m", "mutmut", "apply", str(i)], cwd=work, env=env, capture_output=True,
                                text=True)
            if ap.returncode != 0:  # left as it was (survived)
                print(f"mutation: recheck: mutmut apply {i} failed: {(ap.stdout + ap.stderr)[-300:]}", file=sys.stderr)
                continue
            try:
                rc = subprocess.run(shlex.split(runner), cwd=work, env=env, capture_output=True, timeout=300).returncode
            except subprocess.TimeoutExpired:
                rc = 1  # as mutmut counts a time-out: caught
            finally:
                for t in target.split(","):
                    shutil.copy2(ROOT / t, work / t)
            if rc == 1:  # mutmut's rule: exit status 1 (tests failed) is a kill
                db.execute("UPDATE Mutant SET status = 'ok_killed' WHERE id = ?", (i,))
                db.commit()


def run_module(name: str, py: str) -> dict:
    target, tests = MODULES[name]
    # MUTATION_JOBS shards run side by side, each in its own scratch copy (mutmut mutates in place).
    jobs = max(1, int(os.environ.get("MUTATION_JOBS", "1")))
    keep = os.environ.get("MUTATION_WORKDIR")
    with tempfile.TemporaryDirectory(prefix=f"flytrack-mut-{name}-") as tmp:
        base = Path(keep) / name if keep else Path(tmp)
        works = [base / f"shard{k}" for k in range(jobs)]
        args = ["-x", "-q", "-p", "no:cacheprovider", *tests]
        t0 = time.monotonic()
        servers: list[subprocess.Popen] = []
        runs: list[subprocess.Popen] = []
        recheck = bool(os.environ.get("MUTATION_RECHECK"))
        if recheck and not (keep and all((w / ".mutmut-cache").exists() and (w / "host").is_dir() for w in works)):
            raise RuntimeError("MUTATION_RECHECK needs the MUTATION_WORKDIR (and MUTATION_JOBS) of a finished run")
        try:
            for k, work in enumerate(works):
                if recheck:
                    # Survivors of that run against the code and tests as they are now (tests only added
                    # since: a mutant they killed stays killed). The whole host tree is copied again, the
                    # module under test too: mutmut re-locates each mutant's line in it; the mutants of a
                    # line changed or removed since drop out of mutmut's cache (no longer counted).
                    shutil.rmtree(work / "host")
                    shutil.copytree(ROOT / "host", work / "host",
                                    ignore=shutil.ignore_patterns("__pycache__", ".hypothesis"))
                    (work / ".mutation.sock").unlink(missing_ok=True)
                else:
                    _prepare(work)
                if jobs > 1:
                    (work / "mutmut_config.py").write_text(SHARD_CONFIG.format(n=jobs, k=k))
                # One BLAS thread: the fork server must not fork a thread pool.
                env = {**os.environ, "PYTHONPATH": f"{work / 'host'}{os.pathsep}{work}",
                       "PYTHONDONTWRITEBYTECODE": "1", "FLYTRACK_HYPOTHESIS_EXAMPLES": "25",
                       "FLYTRACK_BUILD_DIR": str(ROOT / "build"), "OPENBLAS_NUM_THREADS": "1",
                       "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
                # The modules the tests import, recorded by one ordinary run (which must pass), are
                # preloaded by the fork server (scripts/mutation_forkserver.py), except the mutated
                # module and the modules that import it.
                mods, sock = work / ".mutation-modules.json", work / ".mutation.sock"
                rec = subprocess.run([py, str(FORKSERVER), "record", str(mods), *shlex.split(" ".join(args))],
                                     cwd=work, env=env, capture_output=True, text=True)
                if rec.returncode != 0:
                    raise RuntimeError(f"the tests of {name} fail without mutations:\n{rec.stdout[-3000:]}"
                                       f"{rec.stderr[-2000:]}")
                server = subprocess.Popen([py, str(FORKSERVER), "serve", str(sock), _module_name(target), str(mods)],
                                          cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                          text=True)
                servers.append(server)
                ready = server.stderr.readline() if server.stderr else ""
                if "preloaded" not in ready:
                    raise RuntimeError(f"mutation fork server for {name} did not start: {ready}")
                runner = f"{py} -S {FORKSERVER} run {sock} {' '.join(args)}"
                if recheck:
                    _recheck(work, target, runner, env, py)
                    continue
                cmd = [py, "-m", "mutmut", "run", "--paths-to-mutate", target, "--runner", runner,
                       "--tests-dir", "host/tests", "--no-progress", "--CI"]
                with open(work / ".mutmut.log", "w") as log:  # every test run's output: long
                    runs.append(subprocess.Popen(cmd, cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT))
            for r in runs:
                r.wait()
            outs = [(w / ".mutmut.log").read_text(errors="replace") for w in works]
        finally:
            for p in runs + servers:
                if p.poll() is None:
                    p.kill()
                    p.wait()
        st: dict[str, int] = {}
        shown = ""
        for work, out in zip(works, outs, strict=True):
            # The statuses from mutmut's cache (with --no-progress it prints no counts). "skipped":
            # the other shards' mutants.
            with sqlite3.connect(work / ".mutmut-cache") as db:
                for status, count in db.execute("SELECT status, COUNT(*) FROM Mutant GROUP BY status"):
                    st[status] = st.get(status, 0) + count
                ids = [i for (i,) in db.execute("SELECT id FROM Mutant WHERE status = 'bad_survived' ORDER BY id")]
            if st.get("untested") and not os.environ.get("MUTATION_PARTIAL"):
                raise RuntimeError(f"mutmut left {st['untested']} mutants of {name} untested:\n{out[-2000:]}")
            if os.environ.get("MUTATION_SHOW"):  # the diff of every survivor, to study them
                for i in ids:
                    d = subprocess.run([py, "-m", "mutmut", "show", str(i)], cwd=work, env=env,
                                       capture_output=True, text=True)
                    shown += d.stdout
        killed, survived = st.get("ok_killed", 0), st.get("bad_survived", 0)
        timeout, suspicious = st.get("bad_timeout", 0), st.get("ok_suspicious", 0)
        total = killed + survived + timeout + suspicious
        if total == 0:
            raise RuntimeError(f"mutmut tested no mutant of {name}:\n{outs[0][-2000:]}")
        # A mutant that makes the tests time out or run suspiciously long was detected: counted killed.
        caught = killed + timeout + suspicious
        untested = st.get("untested", 0)  # MUTATION_PARTIAL: a run stopped early, counted apart
        return {"module": name, "file": target, "tests": tests, "mutants": total, "killed": caught,
                "untested": untested,
                "survived": survived, "timeout": timeout, "suspicious": suspicious, "jobs": jobs,
                "kill_rate": caught / total, "seconds": time.monotonic() - t0, "survivor_diffs": shown}


def main() -> int:
    names = os.environ.get("MUTATION_MODULES", "").split() or list(MODULES)
    bad = [n for n in names if n not in MODULES]
    if bad:
        print(f"mutation: unknown module(s) {bad}; choose from {list(MODULES)}", file=sys.stderr)
        return 2
    py = sys.executable
    rows = []
    for n in names:
        print(f"mutation: {n} ({MODULES[n][0]}) ...", flush=True)
        row = run_module(n, py)
        rows.append(row)
        goal = GOAL.get(n)
        verdict = "" if goal is None else (" goal >= 85%: " + ("met" if row["kill_rate"] >= goal else "NOT met"))
        if row["untested"]:
            verdict += f"; PARTIAL: {row['untested']} mutants not tested"
        print(f"mutation: {n}: {row['killed']}/{row['mutants']} mutants killed = {100 * row['kill_rate']:.1f}% "
              f"({row['survived']} survived, {row['timeout']} timed out, {row['seconds']:.0f} s){verdict}",
              flush=True)
        if row["survivor_diffs"]:
            print(row["survivor_diffs"], flush=True)
    tot = sum(r["mutants"] for r in rows)
    kil = sum(r["killed"] for r in rows)
    print(f"mutation: all: {kil}/{tot} killed = {100 * kil / max(tot, 1):.1f}%")
    if os.environ.get("MUTATION_JSON"):
        Path(os.environ["MUTATION_JSON"]).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

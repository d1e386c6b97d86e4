"""Batch re-tracking and export: serial and on a real dask.distributed cluster (a `dask scheduler` and
two `dask worker` processes on loopback, started here), resumed runs, failed tasks, a killed worker."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pandas as pd
import pytest

from flytrack_host.batch import param_sets, plan_retracks, run_batch
from flytrack_host.batch.tasks import RESULT_NAME
from flytrack_host.recording import load_recording

BIN = Path(sys.executable).parent


class Cluster:
    """A scheduler and `n` single-threaded workers, each its own process, as a lab would start them."""

    def __init__(self, tmp: Path, n: int = 2):
        self.file = tmp / "scheduler.json"
        self.procs: list[subprocess.Popen] = []
        log = open(tmp / "dask.log", "wb")  # noqa: SIM115 - closed with the processes
        self.log = log
        self.procs.append(subprocess.Popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                                            "--no-dashboard", "--scheduler-file", self.file],
                                           stdout=log, stderr=log))
        deadline = time.monotonic() + 60
        while not self.file.exists() or not self.file.read_text().strip():
            assert time.monotonic() < deadline, (tmp / "dask.log").read_text()
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written in one go, but give the scheduler its listen()
        self.address = json.loads(self.file.read_text())["address"]
        self.workers = [subprocess.Popen([BIN / "dask", "worker", self.address, "--nthreads", "1", "--no-nanny",
                                          "--no-dashboard", "--name", f"w{i}"], stdout=log, stderr=log)
                        for i in range(n)]
        self.procs += self.workers
        from dask.distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(n, timeout=60)

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        self.log.close()


@pytest.fixture
def cluster(tmp_path):
    c = Cluster(tmp_path)
    yield c
    c.close()


def _flytrack(*args: str | Path, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([BIN / "flytrack", *map(str, args)], capture_output=True, text=True, timeout=300, **kw)


def test_serial_batch_reports_resumes_and_survives_a_bad_recording(recordings, tmp_path):
    bad = tmp_path / "broken.flytrack"
    bad.mkdir()
    (bad / "meta.json").write_text("{not json")
    tasks = plan_retracks([recordings[0], bad, recordings[1]], param_sets([], ["motion_noise_scale=0.1,0.4"]),
                          tmp_path / "out")
    # What a worker killed half-way leaves: a partial output, never taken for a finished one.
    dead = tasks[0].out.with_name(tasks[0].out.name + ".partial-0dead0")
    dead.mkdir(parents=True)
    rep = run_batch(tasks, progress=False, serial=True)
    assert rep.ran == 4 and rep.skipped == 0 and not dead.exists()
    assert [label for label, _ in rep.failures] == ["broken.flytrack [motion_noise_scale-0.1]",
                                                    "broken.flytrack [motion_noise_scale-0.4]"]
    df = pd.DataFrame(rep.rows)
    assert sorted(df["params"]) == ["motion_noise_scale-0.1"] * 2 + ["motion_noise_scale-0.4"] * 2
    # The figures of a clean synthetic flight: 2 animals tracked over nearly every frame, and the
    # estimates reproject onto their points within the 0.5 px noise the scenario adds.
    assert (df["objects"] == 2).all(), df[["name", "params", "objects"]]
    assert (df["coverage"] > 0.97).all() and (df["frames"] == 300).all()
    assert df["reproj_px_mean"].between(0.2, 0.8).all(), df["reproj_px_mean"]
    assert (df["track_len_max"] >= 290).all()
    # The output is a full recording, with the parameters it was tracked with.
    out = load_recording(tasks[0].out)
    assert out.meta["tracking_params"]["motion_noise_scale"] == 0.1
    assert len(out.table("kalman_estimates")) == df.loc[0, "estimates"]
    # Run again: finished outputs are skipped, their rows reported, nothing written twice.
    stamp = (tasks[0].out / RESULT_NAME).stat().st_mtime_ns
    rep2 = run_batch(tasks, progress=False, serial=True)
    assert rep2.skipped == 4 and rep2.ran == 0 and len(rep2.failures) == 2
    assert (tasks[0].out / RESULT_NAME).stat().st_mtime_ns == stamp
    assert sorted(r["output"] for r in rep2.rows) == sorted(r["output"] for r in rep.rows)
    assert not list((tmp_path / "out").rglob("*.partial-*"))


def test_export_on_a_cluster(recordings, cluster, tmp_path):
    r = _flytrack("batch", "export", *recordings[:2], "--braidz", "--csv", "--out", tmp_path / "exp",
                  "--scheduler", cluster.address, "--no-progress")
    assert r.returncode == 0, r.stderr + r.stdout
    assert "2 tasks run, 0 already done" in r.stdout and "on 2 workers" in r.stdout
    for i in (0, 1):
        z = zipfile.ZipFile(tmp_path / "exp" / f"rec{i}" / f"rec{i}.braidz")
        assert "data2d_distorted.csv.gz" in z.namelist()
        assert (tmp_path / "exp" / f"rec{i}" / "csv").is_dir()
    r = _flytrack("batch", "export", *recordings[:2], "--braidz", "--out", tmp_path / "exp",
                  "--scheduler", cluster.address, "--no-progress")
    assert r.returncode == 0 and "0 tasks run, 2 already done" in r.stdout, r.stdout


def test_a_worker_killed_mid_batch_loses_and_duplicates_nothing(recordings, cluster, tmp_path):
    out = tmp_path / "sweep"
    cmd = [BIN / "flytrack", "batch", "retrack", *recordings, "--sweep", "motion_noise_scale=0.1,0.3",
           "--out", out, "--scheduler", cluster.address, "--no-progress"]
    batch = subprocess.Popen(list(map(str, cmd)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    from dask.distributed import Client

    victim = cluster.workers[0]
    with Client(cluster.address, timeout="30s") as client:
        addr = next(a for a, w in client.scheduler_info(n_workers=-1)["workers"].items() if w["name"] == "w0")
        deadline = time.monotonic() + 120
        # Kill w0 while it is running a task, once the batch is under way (a first output is done).
        while True:
            assert batch.poll() is None and time.monotonic() < deadline, batch.communicate()
            busy = client.processing(workers=[addr]).get(addr, [])
            if busy and list(out.rglob(RESULT_NAME)):
                break
            time.sleep(0.01)
    os.kill(victim.pid, signal.SIGKILL)
    # What w0 had in hand and had not finished (a task may finish between the query and the kill).
    finished = {p.parent.relative_to(out).as_posix() for p in out.rglob(RESULT_NAME)}
    lost = {Path(k.split("-", 2)[2]).relative_to(out).as_posix() for k in busy} - finished
    stdout, stderr = batch.communicate(timeout=300)
    assert batch.returncode == 0, stderr + stdout
    done = sorted(p.parent.relative_to(out).as_posix() for p in out.rglob(RESULT_NAME))
    assert done == sorted(f"rec{i}/motion_noise_scale-{s}.flytrack" for i in range(4) for s in ("0.1", "0.3"))
    df = pd.read_parquet(out / "results.parquet")
    assert len(df) == 8 and not df.duplicated(["name", "params"]).any()
    assert (df["objects"] == 2).all() and (df["coverage"] > 0.97).all()
    assert df.equals(pd.read_csv(out / "results.csv").astype(df.dtypes.to_dict()))
    assert (out / "results.png").stat().st_size > 10_000
    assert not list(out.rglob("*.partial-*"))
    # What the killed worker had in hand was done again by the survivor, once.
    assert lost and lost <= set(done)
    redone = df[df["output"].map(lambda o: Path(o).relative_to(out).as_posix() in lost)]
    assert len(redone) == len(lost) and not redone["worker"].str.endswith(f":{victim.pid}").any()


def test_braidz_and_flytrack_sources_in_one_batch(recordings, tmp_path):
    from flytrack_host.io.braidz import export_braidz

    bz = tmp_path / "lab.braidz"
    export_braidz(load_recording(recordings[2]), bz)
    tasks = plan_retracks([bz, recordings[3]], param_sets(), tmp_path / "out")
    rep = run_batch(tasks, progress=False, serial=True)
    assert not rep.failures and rep.ran == 2
    rows = {r["name"]: r for r in rep.rows}
    assert set(rows) == {"lab", "rec3"} and rows["lab"]["objects"] == 2 and rows["lab"]["coverage"] > 0.97


def test_a_task_that_tracks_nothing_says_why(recordings, tmp_path, capsys):
    """As `flytrack retrack` does: a task whose 2D points gave no estimate carries the reason, with numbers,
    in its results row and on the console, instead of a silent 0."""
    import typer

    from flytrack_host.batch.cli import _finish

    bad = tmp_path / "broken.flytrack"
    bad.mkdir()
    (bad / "meta.json").write_text("{not json")
    tasks = plan_retracks([recordings[0], bad], param_sets(["death_position_std_m=1e-9"], []), tmp_path / "out")
    rep = run_batch(tasks, progress=False, serial=True)
    assert len(rep.failures) == 1 and rep.rows[0]["objects"] == 0
    assert "every new target died before confirmation" in rep.rows[0]["why_no_estimates"]
    with pytest.raises(typer.Exit):
        _finish(rep, tmp_path / "out", plot=False)
    err = " ".join(capsys.readouterr().err.split())
    assert "no estimates rec0 [death_position_std_m-1e-9]: every new target died" in err, err
    assert "failed broken.flytrack [death_position_std_m-1e-9]: " in err, err  # not taken for rich markup
    assert "died before confirmation" in pd.read_csv(tmp_path / "out" / "results.csv")["why_no_estimates"][0]


def test_a_bad_recording_on_a_local_cluster_is_one_line_not_a_worker_traceback(tmp_path):
    bad = tmp_path / "broken.flytrack"
    bad.mkdir()
    (bad / "meta.json").write_text("{not json")
    r = _flytrack("batch", "retrack", bad, "--out", tmp_path / "out", "--workers", "1", "--no-progress")
    assert r.returncode == 1, r.stdout + r.stderr
    err = " ".join(r.stderr.split())
    assert "failed broken.flytrack [base]: " in err, err
    assert "Traceback" not in r.stderr and "Compute Failed" not in r.stderr, r.stderr

"""A full disk, for real: `flytrack run` records into a 2 MB tmpfs mounted by the test (root only; the
test is skipped with the reason otherwise). The run must say so and exit non-zero; `flytrack recording
recover` on the full disk must say what to do (no traceback) and, with --out, write the file elsewhere;
the rows written before the disk filled are all there."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.protocol.udp import POINT_DTYPE, FeatureFrame, encode_features
from flytrack_host.recording import load_recording
from flytrack_host.recording.parts import part_dirs
from flytrack_host.util.testing import small_tmpfs

ROOT = Path(__file__).resolve().parents[2]
FLYTRACK = [sys.executable, "-m", "flytrack_host.cli"]


@pytest.fixture
def small_disk(tmp_path):
    with small_tmpfs(tmp_path / "small", "2m") as mnt:
        yield mnt


def _points(n: int, k: int) -> np.ndarray:
    p = np.zeros(n, POINT_DTYPE)
    p["x_dist"] = np.arange(n) + k * 0.01
    p["y_dist"] = 7.0
    p["area"] = 3.0
    p["orientation"] = np.nan
    p["eccentricity"] = np.nan
    return p


@pytest.mark.slow
def test_disk_full_exits_non_zero_and_recover_says_what_to_do(small_disk, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "full"\n[trigger]\nkind = "software"\nfps = 100.0\n[host]\nlisten = "127.0.0.1:7000"\n'
                   '[recording]\nfolder = "rec"\nflush_interval_s = 0.2\n'
                   '[[cameras]]\nname = "a"\nindex = 0\nedge = "127.0.0.1"\n'
                   '[[cameras]]\nname = "b"\nindex = 1\nedge = "127.0.0.1"\n')
    rec = small_disk / "run.flytrack"
    proc = subprocess.Popen(FLYTRACK + ["run", str(rig), "--bind", "127.0.0.1:0", "--recording", str(rec),
                                        "--seconds", "6"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    line = proc.stdout.readline()
    assert line.startswith("listening on"), (line, proc.stderr.read() if proc.poll() is not None else "")
    port = int(line.split()[2].rstrip(";").rsplit(":", 1)[1])
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.monotonic()
    k = 0
    # 2 cameras x 100 fps x 60 points x ~100 bytes a row: ~1.2 MB/s, so the 2 MB disk fills in ~2 s.
    while time.monotonic() - t0 < 4.0:
        for cam in (0, 1):
            ff = FeatureFrame(camera_index=cam, seq=k, camera_frame=k, trigger_frame=k, total_points=60,
                              points=_points(60, k))
            for d in encode_features(ff):
                sock.sendto(d, ("127.0.0.1", port))
        k += 1
        time.sleep(max(0.0, t0 + k / 100.0 - time.monotonic()))
    out, err = proc.communicate(timeout=60)
    text = out + err
    assert proc.returncode == 3, text[-3000:]
    assert "recording incomplete" in text and "write errors" in text, text[-3000:]
    assert "No space left" in text or "ENOSPC" in text or "disk is full" in text, text[-3000:]

    # recover on the full disk: one clear line, what to do, exit 2; no traceback
    r = subprocess.run(FLYTRACK + ["recording", "recover", str(rec)], capture_output=True, text=True, cwd=ROOT)
    said = r.stdout + r.stderr
    if r.returncode == 0:  # finalising at stop fitted after all: then the files are there and open
        assert all((p / "recording.h5").exists() for p in part_dirs(rec))
    else:
        assert r.returncode == 2 and "Traceback" not in said, said
        assert "disk is full" in said and "--out" in said and "Nothing is lost" in said, said
        assert not list(rec.rglob("*.tmp")), "a failed recover must not leave its partial file behind"
    # ... and with --out on another disk it works (a recording in parts: a folder of its parts' HDF5
    # files); every row written before the disk filled is there.
    dest = tmp_path / "elsewhere.flytrack"
    r = subprocess.run(FLYTRACK + ["recording", "recover", str(rec), "--out", str(dest), "--force"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    d2 = load_recording(dest).table("data2d_distorted")
    assert len(d2) > 1000
    frames = np.unique(d2["camera_frame"]).astype(np.int64)
    # Every frame up to the first failed write is there, from frame 0 (the disk held ~3 s of them);
    # what came after is what the run reported lost.
    first_gap = int(np.argmax(np.diff(frames) != 1)) if np.any(np.diff(frames) != 1) else len(frames) - 1
    assert frames[0] == 0 and first_gap >= 100, frames
    lost = int(text.split(" rows lost")[0].rsplit(" ", 1)[-1])
    assert lost > 0

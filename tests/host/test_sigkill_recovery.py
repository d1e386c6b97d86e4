"""`flytrack run` records real UDP input in a subprocess; SIGKILL it mid-run; `flytrack recording
recover` completes the recording; what was sent up to the last second (the flush interval) is there,
bit for bit, and nothing recorded is anything that was not sent."""

from __future__ import annotations

import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from flytrack_host.protocol.udp import POINT_DTYPE, FeatureFrame, encode_features
from flytrack_host.recording import load_recording

ROOT = Path(__file__).resolve().parents[2]
FLYTRACK = [sys.executable, "-m", "flytrack_host.cli"]
FPS = 100.0
FLUSH_S = 1.0


def points(cam: int, frame: int) -> np.ndarray:
    p = np.zeros(3, POINT_DTYPE)
    p["x_dist"] = 10.0 + cam + np.arange(3) + frame * 0.5
    p["y_dist"] = 20.0 + frame * 0.25
    p["x_undist"], p["y_undist"] = p["x_dist"], p["y_dist"]
    p["area"] = 4.0 + np.arange(3)
    p["orientation"] = np.nan
    p["eccentricity"] = np.nan
    return p


def wait_line(proc: subprocess.Popen, prefix: str, timeout: float) -> str:
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if sel.select(timeout=0.2):
            line = proc.stdout.readline()
            if line.startswith(prefix):
                return line
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"no {prefix!r} line from flytrack run (rc {proc.poll()}): {proc.stderr.read()}")


def test_sigkill_then_recover_keeps_everything_up_to_the_last_second(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(
        'name = "killtest"\n[trigger]\nkind = "software"\nfps = 100.0\n'
        '[host]\nlisten = "127.0.0.1:7000"\n'
        f'[recording]\nfolder = "rec"\nflush_interval_s = {FLUSH_S}\n'
        '[[cameras]]\nname = "a"\nindex = 0\nedge = "127.0.0.1"\n'
        '[[cameras]]\nname = "b"\nindex = 1\nedge = "127.0.0.1"\n'
    )
    out = tmp_path / "run.flytrack"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(FLYTRACK + ["run", str(rig), "--bind", "127.0.0.1:0", "--recording", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        line = wait_line(proc, "listening on", 60)
        port = int(line.split()[2].rstrip(";").rsplit(":", 1)[1])
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sent_at: dict[int, float] = {}
        seq = [0, 0]
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < 2.6:
            for cam in (0, 1):
                ff = FeatureFrame(camera_index=cam, seq=seq[cam], camera_frame=k, trigger_frame=k, total_points=3,
                                  points=points(cam, k))
                for d in encode_features(ff):
                    sock.sendto(d, ("127.0.0.1", port))
                seq[cam] += 1
            sent_at[k] = time.time()
            k += 1
            time.sleep(max(0.0, t0 + k / FPS - time.monotonic()))
        t_kill = time.time()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        sock.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "recording.h5").exists()

    r = subprocess.run(FLYTRACK + ["recording", "recover", str(out)], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "recovered" in r.stdout

    d2 = load_recording(out).table("data2d_distorted")
    recorded = {(int(c), int(f)) for c, f in zip(d2["camera_index"], d2["camera_frame"], strict=True)}
    # Everything sent more than the flush interval (plus scheduling slack) before the kill is there.
    must = [f for f, t in sent_at.items() if t < t_kill - FLUSH_S - 0.3]
    assert len(must) > 100
    missing = [(c, f) for f in must for c in (0, 1) if (c, f) not in recorded]
    assert not missing, missing[:10]
    # ... and equals what was sent, point by point; nothing recorded that was not sent.
    for (c, f) in recorded:
        assert f in sent_at
        rows = d2[(d2["camera_index"] == c) & (d2["camera_frame"] == f)]
        rows = rows[np.argsort(rows["frame_pt_idx"])]
        sent = points(c, f)
        assert len(rows) == 3
        for name in ("x_dist", "y_dist", "area"):
            assert np.array_equal(rows[name], sent[name]), (c, f, name)
        assert np.all(rows["trigger_frame"] == f)
    print(f"sent {len(sent_at)} frames per camera, recovered {len(recorded) // 2}; "
          f"lost at the end {len(sent_at) - len(recorded) // 2} frames "
          f"({(len(sent_at) - len(recorded) // 2) / FPS:.2f} s of {FLUSH_S} s allowed + slack)")

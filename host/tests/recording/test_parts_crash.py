"""A recording in parts killed with SIGKILL in the middle of a part: the parts before it are whole (and
finalised, or finalised by `recording recover`), the part being written loses at most its rows not yet
handed to the kernel, and `flytrack recording recover` completes it as it does an unparted recording."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.recording import load_recording
from flytrack_host.recording.parts import part_dirs
from flytrack_host.recording.schema import H5_NAME

FLUSH_S = 0.2
ROWS = 4  # 2D rows a frame

# Frames of known rows, each frame one item, paced at 500 frames/s, into parts of 400 kB (1.2 s); every 25 frames
# it says how many frames it has handed to the recorder and when (wall clock).
WRITER = f"""
import sys, time
import numpy as np
from flytrack_host.recording import Recorder
from flytrack_host.recording.parts import PartPolicy
from flytrack_host.recording.schema import DATA2D, KALMAN
rec = Recorder(sys.argv[1], flush_interval_s={FLUSH_S}, parts=PartPolicy(bytes=400_000))
rec.start()
f = 0
t0 = time.monotonic()
while True:
    d = np.zeros({ROWS}, DATA2D)
    d["trigger_frame"], d["frame_pt_idx"], d["x_dist"] = f, np.arange({ROWS}), f * 0.25 + np.arange({ROWS})
    k = np.zeros(1, KALMAN)
    k["trigger_frame"], k["obj_id"], k["x"] = f, 7, f * 0.001
    rec.append_many([("data2d_distorted", d), ("kalman_estimates", k)])
    f += 1
    if f % 25 == 0:
        print(f, time.time(), flush=True)
    time.sleep(max(0.0, t0 + f / 500 - time.monotonic()))
"""


def test_sigkill_mid_part_loses_at_most_that_parts_tail(tmp_path) -> None:
    out = tmp_path / "killed.flytrack"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out)], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    handed: list[tuple[int, float]] = []
    try:
        # Until the writer is in the middle of its 4th part or a later one (the newest part a third to two
        # thirds full: its 2D rows are 65 % of its bytes), with at least two parts finalised in the background.
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            n, t = line.split()
            handed.append((int(n), float(t)))
            parts = part_dirs(out)
            d2 = parts[-1] / "data2d_distorted.bin" if parts else None
            if (len(parts) >= 4 and d2 is not None and d2.exists() and 90_000 < d2.stat().st_size < 170_000
                    and sum((p / H5_NAME).exists() for p in parts) >= 2):
                break
        t_kill = time.time()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    parts = part_dirs(out)
    assert proc.returncode == -signal.SIGKILL and len(parts) >= 4, (proc.returncode, parts)
    last = parts[-1]
    assert not (last / H5_NAME).exists()  # the part being written when it died
    before = [p for p in parts[:-1]]
    finalised_before = [p.name for p in before if (p / H5_NAME).exists()]

    r = CliRunner().invoke(app, ["recording", "recover", str(out)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "recovered" in r.output and last.name in r.output
    for name in finalised_before:
        assert name not in r.output.split("(")[1].split(")")[0]  # those were whole already: left alone
    assert all((p / H5_NAME).exists() for p in part_dirs(out))

    rec = load_recording(out)
    d2, k = rec.table("data2d_distorted"), rec.table("kalman_estimates")
    n = len(k)
    # Every frame once, in order, from frame 0 on, bit for bit: nothing lost in the middle, nothing twice.
    assert np.array_equal(k["trigger_frame"], np.arange(n)) and np.allclose(k["x"], np.arange(n) * 0.001)
    assert len(d2) == ROWS * n and np.array_equal(d2["trigger_frame"], np.repeat(np.arange(n), ROWS))
    assert np.array_equal(d2["x_dist"], (np.repeat(np.arange(n), ROWS) * 0.25 + np.tile(np.arange(ROWS), n))
                          .astype(np.float32))
    # The parts before the last are whole: the last part starts with the frame after them.
    in_last = load_recording(last).table("kalman_estimates")["trigger_frame"]
    n_before = sum(len(load_recording(p).table("kalman_estimates")) for p in before)
    assert len(in_last) and in_last[0] == n_before
    first_of_last = int(in_last[0])
    # Lost: at most the last part's tail not yet handed to the kernel (frames handed more than a flush
    # interval and some slack before the kill are all there).
    must = max((f for f, t in handed if t < t_kill - FLUSH_S - 0.3), default=0)
    assert n >= must and n > n_before, (n, must, n_before)
    sent = handed[-1][0] if handed else 0
    print(f"{len(parts)} parts, {len(finalised_before)} finalised in the background before the kill; frames handed "
          f">= {sent}, recovered {n} (the last part from frame {first_of_last}); lost at most {sent + 25 - n} "
          f"frames = {(sent + 25 - n) / 500:.3f} s of the last part")


def test_recover_out_writes_a_recording_in_parts_elsewhere(tmp_path) -> None:
    from flytrack_host.recording import Recorder
    from flytrack_host.recording.parts import PartPolicy
    from flytrack_host.recording.schema import DATA2D

    src = tmp_path / "src.flytrack"
    rec = Recorder(src, flush_interval_s=0.05, on_full="block", parts=PartPolicy(bytes=20_000, finalize="none"))
    rec.start()
    rec.attach("rig.toml", b'name = "r"\n')
    for f in range(500):
        d = np.zeros(2, DATA2D)
        d["trigger_frame"] = f
        rec.append("data2d_distorted", d)
    rec.stop(finalize=False)
    dest = Path(tmp_path / "other_disk" / "src.flytrack")
    bad = CliRunner().invoke(app, ["recording", "recover", str(src), "--out", str(tmp_path / "x.h5")])
    assert bad.exit_code == 2 and "give --out a folder" in " ".join(bad.output.split())
    r = CliRunner().invoke(app, ["recording", "recover", str(src), "--out", str(dest)])
    assert r.exit_code == 0, r.output
    assert not any((p / H5_NAME).exists() for p in part_dirs(src))  # the source is left as it was
    back = load_recording(dest)
    assert np.array_equal(back.table("data2d_distorted")["trigger_frame"], np.repeat(np.arange(500), 2))
    assert back.files == {"rig.toml": b'name = "r"\n'} and not list(dest.rglob("*.bin"))

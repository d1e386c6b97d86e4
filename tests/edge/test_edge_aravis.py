"""flytrack-edge against a real GenICam camera protocol: Aravis's fake GigE Vision camera on loopback.

The camera is opened by its address (127.0.0.1) and by its listed name (Aravis-Fake-<serial>, as
`arv-tool-0.8` lists it). By name, discovery can answer through another interface (eth0) than the one
that reaches the camera (lo); Aravis then streams to eth0's address, which no socket on eth0 sees, and
no frame arrived (issue 4) until source_aravis.c reopened such a camera on the routed address."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.protocol import EdgeStatus, FeatureFrame

FAKE = "arv-fake-gv-camera-0.8"


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture
def fake_camera():
    if shutil.which(FAKE) is None:
        pytest.fail(f"{FAKE} is missing: install aravis-tools (scripts/apt-packages.txt, make setup)")
    serial = f"FT{os.getpid() % 100000}"
    proc = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", serial], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    time.sleep(0.7)
    if proc.poll() is not None:
        pytest.fail(f"the fake camera did not start: {proc.stdout.read().decode()}")
    proc.serial = serial
    yield proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("by", ["address", "name"])
def test_aravis_fake_camera_streams_features(edge_bin: Path, receiver, fake_camera, by: str) -> None:
    camera = "127.0.0.1" if by == "address" else f"Aravis-Fake-{fake_camera.serial}"
    cmd = [str(edge_bin), "--source", "aravis", "--input", camera, "--fps", "50",
           "--host", "127.0.0.1", "--port", str(receiver.port), "--control-port", str(_free_port()),
           "--camera-index", "1", "--max-frames", "25", "--vanish-timeout-ms", "5000",
           "--bg-update-interval", "5"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    receiver.poll(0.5)
    fr = [m for m in receiver.messages if isinstance(m, FeatureFrame)]
    frames = sorted({m.camera_frame for m in fr})
    assert len(frames) == 25, p.stderr
    assert frames == sorted(frames) and all(m.camera_index == 1 for m in fr)
    assert all(m.device_timestamp_ns > 0 for m in fr)  # the camera's own timestamps
    for m in fr:
        assert m.n_points <= 32 and m.part_index < m.part_count
    # The fake camera's test pattern moves: after the background, some frames give points.
    assert sum(m.n_points for m in fr) > 0
    # The fake camera's image is Aravis's diagonal ramp, value (x + y + frame id) mod 255 (times a gain
    # scale): as it moves, the wrap from 254 to 0 leaves stripes along x + y = const, 255 apart in x + y.
    # On the square 512 x 512 image every stripe's centre lies on the diagonal x = y, each stripe is
    # oriented at -45 degrees (image axes, y down), the stripes of a frame are 127.5 px apart in x, four of
    # them, and the difference at the wrap is nearly full scale.
    with_points = [m for m in fr if m.n_points]
    assert with_points
    for m in with_points:
        pts = m.points
        assert m.n_points == 4, (m.camera_frame, pts)
        np.testing.assert_allclose(pts["x_dist"], pts["y_dist"], atol=0.05)
        np.testing.assert_allclose(pts["orientation"], -np.pi / 4, atol=1e-3)
        xs = np.sort(pts["x_dist"])
        np.testing.assert_allclose(np.diff(xs), 127.5, atol=1.0)
        assert np.all((xs > 0) & (xs < 512)) and np.all(pts["peak_diff"] >= 200)
        # Each stripe is k adjacent lines x + y = const around 2 x_c (k: how far the ramp moved since the
        # background was taken, the same for every stripe of a frame), each as long as the image lets it
        # be: 2 x_c + 1 pixels up to the anti-diagonal, 1023 - 2 x_c beyond (a stripe near a corner is
        # short: 89 px a line at x_c = 44). Measured: k = 1 to 10, every stripe of a frame within 0.006 of it.
        order = np.argsort(pts["x_dist"])
        lines = np.minimum(2 * xs + 1, 1023 - 2 * xs)
        k = pts["area"][order] / lines
        assert np.allclose(k, np.round(k[np.argmax(lines)]), atol=3.0 / lines.min()) and k.max() >= 0.99, k
    st = [m for m in receiver.messages if isinstance(m, EdgeStatus)]
    assert st and st[-1].width == 512 and st[-1].height == 512 and st[-1].frames_seen == 25


def test_camera_that_vanishes_is_an_error_exit(edge_bin: Path, receiver, fake_camera) -> None:
    cmd = [str(edge_bin), "--source", "aravis", "--input", "127.0.0.1", "--fps", "50",
           "--host", "127.0.0.1", "--port", str(receiver.port), "--control-port", str(_free_port()),
           "--vanish-timeout-ms", "1500"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    got = receiver.wait_for(lambda m: isinstance(m, FeatureFrame) and m.camera_frame >= 3, 20.0)
    assert got, "no frames from the fake camera"
    fake_camera.kill()
    fake_camera.wait()
    rc = p.wait(30)
    err = p.stderr.read()
    assert rc == 3, err
    assert "camera vanished" in err
    receiver.poll(0.3)
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert last.state == 2 and "vanished" in last.last_error

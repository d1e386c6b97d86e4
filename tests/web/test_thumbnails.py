"""Camera thumbnails: a real flytrack-edge asked for full frames (CONTROL SEND_FULL_IMAGE on the rig's
control port) sends IMAGE chunks to the real host pipeline; the live server puts them together and
serves the page a PNG equal to the frame, scaled down."""

from __future__ import annotations

import json
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pytest

from flytrack_host.live.web.server import LiveServer
from flytrack_host.pipeline import HostPipeline
from flytrack_host.rig import parse_rig
from flytrack_host.sim.run import find_edge_binary

W, H = 320, 240


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_edge_full_frames_become_the_pages_thumbnails():
    import cv2

    try:
        edge = find_edge_binary()
    except Exception as exc:
        pytest.fail(f"{exc}")
    cport = _free_udp_port()
    rig = parse_rig({"name": "thumbs", "trigger": {"kind": "software", "fps": 50.0},
                     "host": {"listen": "127.0.0.1:7000", "control_port": cport},
                     "cameras": [{"name": "cam1", "index": 0, "edge": "127.0.0.1"}]})
    pipe = HostPipeline(rig, {}, record=False, bind="127.0.0.1:0", tracker_factory=None)
    server = LiveServer("127.0.0.1", 0, thumbnails_every_s=0.3)
    server.attach(pipe)
    pipe.start()
    proc = subprocess.Popen([str(edge), "--host", "127.0.0.1", "--port", str(pipe.address[1]), "--control-port",
                             str(cport), "--bind", "127.0.0.1", "--source", "raw", "--input", "-", "--width", str(W),
                             "--height", str(H), "--camera-index", "0", "--camera-name", "cam1"],
                            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    yy, xx = np.mgrid[0:H, 0:W]
    frame = ((xx * 255) // W ^ (yy * 3)).astype(np.uint8)  # a pattern that shows any misplaced chunk
    try:
        end = time.monotonic() + 20
        while 0 not in server.thumbs.latest and time.monotonic() < end:
            proc.stdin.write(frame.tobytes())
            proc.stdin.flush()
            time.sleep(0.02)
        assert 0 in server.thumbs.latest, f"no thumbnail: {server.stats()}"
        png = urllib.request.urlopen(server.url + "thumb/0.png", timeout=10).read()
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape == (120, 160)
        assert np.array_equal(img, cv2.resize(frame, (160, 120), interpolation=cv2.INTER_AREA))
        time.sleep(0.6)  # a page state after the thumbnail
        state = json.loads(urllib.request.urlopen(server.url + "api/state", timeout=10).read())
        thumb = state["cameras"][0]["thumbnail"]
        assert thumb is not None and thumb["id"] >= 1
        st = server.stats()
        assert st["thumbnail_requests"] >= 1 and st["thumbnails"] >= 1
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(server.url + "thumb/7.png", timeout=10)
        assert e.value.code == 404
    finally:
        proc.stdin.close()
        proc.wait(10)
        pipe.stop()

"""`flytrack run` starts the live outputs (--http, --pose) and refuses bad settings in one line."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from flytrack_host.live.braid import open_event_stream

ROOT = Path(__file__).resolve().parents[3]


def _rig(tmp_path: Path) -> Path:
    rig = (ROOT / "examples" / "rig.toml").read_text()
    rig = rig.replace('folder = "recordings"', f'folder = "{tmp_path / "rec"}"')
    path = tmp_path / "rig.toml"
    path.write_text(rig)
    return path


def _run(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flytrack_host.cli", "run", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def test_run_serves_events_and_pose_then_stops(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as pose_sock:
        pose_sock.bind(("127.0.0.1", 0))
        pose_sock.settimeout(10)
        p = _run([str(_rig(tmp_path)), "--no-trigger", "--seconds", "3", "--no-record", "--bind", "127.0.0.1:0",
                  "--http", "127.0.0.1:0",
                  "--pose", f"127.0.0.1:{pose_sock.getsockname()[1]}", "--pose-rate", "50"])
        try:
            first = p.stdout.readline()
            assert first.startswith("listening on 127.0.0.1:")  # still the first line, for scripts
            banner = p.stdout.readline()
            m = re.match(r"live view: (http://127\.0\.0\.1:\d+/)\s", banner)
            assert m, banner
            assert p.stdout.readline().startswith("pose stream: 50 Hz to 127.0.0.1:")
            stats = json.loads(urllib.request.urlopen(m.group(1) + "api/stats", timeout=10).read())
            assert stats["clients"] == 0 and stats["unauthorised"] == 0
            ev = open_event_stream(m.group(1) + "events", timeout=10)
            assert ev.headers["Content-Type"] == "text/event-stream"
            data, _ = pose_sock.recvfrom(2048)  # no camera: NO_OBJECT datagrams at the rate
            assert data[:4] == b"FTPS" and data[5] == 2
            t0 = time.monotonic()
            assert ev.read() == b""  # the run ends after --seconds: the stream ends cleanly
            assert time.monotonic() - t0 < 15
        finally:
            out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err


def test_run_refuses_a_busy_http_address_and_bad_pose_settings(tmp_path):
    from typer.testing import CliRunner

    from flytrack_host.cli import app

    rig = _rig(tmp_path)
    base = ["run", str(rig), "--no-trigger", "--seconds", "1", "--no-record", "--bind", "127.0.0.1:0"]
    env = {"COLUMNS": "200", "NO_COLOR": "1"}
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = CliRunner().invoke(app, [*base, "--http", f"127.0.0.1:{port}"], env=env)
    assert r.exit_code == 2
    assert "cannot listen on" in r.output and f"127.0.0.1:{port}" in r.output
    for bad, msg in ((["--pose-lock", "first"], "pose lock must be auto, all or an object id"),
                     (["--http", "host:web"], "bad port"),
                     (["--pose", "127.0.0.1:7300", "--pose-rate", "0"], "pose rate must be 1..2000 Hz")):
        r = CliRunner().invoke(app, [*base, "--http", "off", *bad], env=env)
        assert r.exit_code == 2, (bad, r.output)
        assert msg in " ".join(r.output.split()), (bad, r.output)


def test_default_port_taken_warns_and_runs_without_the_live_view(tmp_path):
    """`flytrack run` with the default --http: a taken port is a warning, not a stopped run (tracking
    matters more than the view); an address the user gave must bind (tested above)."""
    from flytrack_host.live.launch import DEFAULT_HTTP, LiveOutputs
    from flytrack_host.pipeline import HostPipeline
    from flytrack_host.rig import load_rig

    pipe = HostPipeline(load_rig(_rig(tmp_path)), {}, record=False)
    assert LiveOutputs.from_options(http=DEFAULT_HTTP).http_required is False
    assert LiveOutputs.from_options(http="127.0.0.1:9999").http_required is True
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        out = LiveOutputs(http=("127.0.0.1", busy.getsockname()[1]), http_required=False)
        lines: list[str] = []
        out.attach(pipe, echo=lines.append)
    assert out.server is None and pipe.sinks == []
    assert lines and lines[0].startswith("warning: live view and Braid events off: cannot listen on 127.0.0.1:")

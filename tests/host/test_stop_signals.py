"""Stops cleanly (issue 24): `flytrack demo`, `flytrack run` and the fault suite, each in a process of its
own, sent SIGINT (Ctrl-C), SIGTERM (a service manager, a supervisor) or SIGKILL once running. Every
process it started (its descendants, found in /proc before the signal) must be gone within a deadline,
whatever the signal; after SIGINT or SIGTERM the recording must be finalised (every part its recording.h5, readable,
with the frames received) and the exit code must be Ctrl-C's.

Descendants are read from /proc/<pid>/task/*/children, and known by (pid, start time) so that a pid
used again by another process is not taken for a survivor; a zombie (ended, not yet reaped by whoever
inherited it) counts as gone. Every wait is for a condition, with a deadline.
"""

from __future__ import annotations

import contextlib
import os
import signal
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

ROOT = Path(__file__).resolve().parents[2]
FLYTRACK = [sys.executable, "-m", "flytrack_host.cli"]
# Ctrl-C's exit code, per command: `flytrack run` stops on Ctrl-C as on its --seconds (0, or 3 when the
# recording lost data); `flytrack demo` ends without its report (130, 128 + SIGINT, as typer does).
CTRL_C_EXIT = {"run": 0, "demo": 130}
STOP_DEADLINE_S = 60.0  # SIGINT / SIGTERM: the command finalises its recording and exits within this
GONE_DEADLINE_S = 10.0  # then (or after SIGKILL) every descendant is gone within this
SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGKILL]


# --- processes, from /proc ------------------------------------------------------------------------
def _stat(pid: int) -> tuple[str, int] | None:
    """(state letter, start time in clock ticks) of a process, None when there is none."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return fields[0], int(fields[19])



def finalised(rec: Path) -> bool:
    """Every part of the recording has its recording.h5 (the demo and `run` record in parts)."""
    parts = part_dirs(rec)
    return bool(parts) and all((p / "recording.h5").exists() for p in parts)

def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def descendants(pid: int) -> dict[int, tuple[int, str]]:
    """Every living descendant of `pid`: pid -> (start time, command line). Zombies are left out."""
    out: dict[int, tuple[int, str]] = {}
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                kids = [int(c) for c in Path(f"/proc/{p}/task/{t}/children").read_text().split()]
            except OSError:
                continue
            for c in kids:
                st = _stat(c)
                if c in out or st is None:
                    continue
                if st[0] not in "ZX":
                    out[c] = (st[1], _cmdline(c))
                todo.append(c)
    return out


def _is_edge(cmd: str) -> bool:
    """A `flytrack-edge` running (not a wrapper about to start one)."""
    return bool(cmd) and Path(cmd.split()[0]).name == "flytrack-edge"


def _alive(pid: int, start: int) -> bool:
    st = _stat(pid)
    return st is not None and st[1] == start and st[0] not in "ZX"


def kill_leftovers(procs: dict[int, tuple[int, str]]) -> None:
    """The test's own clean-up when it failed: nothing it started may outlive it."""
    for pid, (start, _) in procs.items():
        if _alive(pid, start):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


class Command:
    """A FlyTrack command in a process of its own, its output in files (a pipe nobody reads while it
    stops could block it)."""

    def __init__(self, args: list[str], tmp: Path, **env: str) -> None:
        self.out_path, self.err_path = tmp / "stdout.txt", tmp / "stderr.txt"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(FLYTRACK[:1] + args, cwd=ROOT, stdout=out, stderr=err, text=True,
                                         env=dict(os.environ, PYTHONUNBUFFERED="1", **env))
        self.pid = self.proc.pid

    @property
    def stdout(self) -> str:
        return self.out_path.read_text(errors="replace")

    @property
    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def wait_for(self, what: str, cond, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if self.proc.poll() is not None:
                raise AssertionError(f"exited with {self.proc.returncode} before {what}: {self.stderr[-3000:]}")
            if time.monotonic() > end:
                raise AssertionError(f"not {what} within {timeout_s:.0f} s: {self.stderr[-3000:]}")
            time.sleep(0.05)

    def stop(self, sig: int) -> tuple[dict[int, tuple[int, str]], dict[int, float], float]:
        """Signals the command once its descendants are recorded, then watches them and it: returns
        the descendants, the seconds from the signal until each was gone, and until the command
        exited. Fails when the command is not gone within STOP_DEADLINE_S or a descendant within
        GONE_DEADLINE_S after it."""
        before = descendants(self.pid)
        gone: dict[int, float] = {}
        t_exit = None
        t0 = time.monotonic()
        self.proc.send_signal(sig)
        try:
            while True:
                now = time.monotonic() - t0
                for pid, (start, _) in before.items():
                    if pid not in gone and not _alive(pid, start):
                        gone[pid] = now
                if t_exit is None and self.proc.poll() is not None:
                    t_exit = now
                if t_exit is not None and len(gone) == len(before):
                    return before, gone, t_exit
                if t_exit is None and now > STOP_DEADLINE_S:
                    raise AssertionError(f"{signal.Signals(sig).name}: not ended within {STOP_DEADLINE_S:.0f} s: "
                                         f"{self.stderr[-3000:]}")
                if t_exit is not None and now > t_exit + GONE_DEADLINE_S:
                    left = {pid: cmd[:160] for pid, (_, cmd) in before.items() if pid not in gone}
                    raise AssertionError(f"{signal.Signals(sig).name}: still running {GONE_DEADLINE_S:.0f} s "
                                         f"after the command ended: {left}")
                time.sleep(0.002)
        finally:
            self.close()
            kill_leftovers(before)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def abandon(self) -> None:
        """The test failed before its signal: end the command and everything it started."""
        kids = descendants(self.pid)
        self.close()
        kill_leftovers(kids)


def report(name: str, sig: int, before: dict[int, tuple[int, str]], gone: dict[int, float], t_exit: float,
           rc: int) -> None:
    """One line of figures (pytest -s shows it): exit code, seconds to exit, to each descendant gone."""
    def kind(cmd: str) -> str:
        words = cmd.split()
        name = Path(words[0]).name if words else "?"
        return " ".join(words[1:4]) if name.startswith("python") else name

    each = ", ".join(f"{kind(before[p][1])} {t:.3f}" for p, t in sorted(gone.items(), key=lambda kv: kv[1]))
    print(f"\n{name} {signal.Signals(sig).name}: exit {rc} {t_exit:.3f} s after the signal; {len(before)} "
          f"descendants, gone after (s): {each or '-'}")


# --- flytrack demo --------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_demo_stops_with_everything_it_started(tmp_path, sig):
    """A long demo (2 cameras, the firmware in simavr where it is built, --serve) signalled once frames
    are being recorded: its edges, its simulated cameras and its trigger end with it; after SIGINT or
    SIGTERM the recording is finalised and it exits 130."""
    out = tmp_path / "demo"
    rec = out / "recording.flytrack"
    demo = Command(FLYTRACK[1:] + ["demo", "--cameras", "2", "--animals", "1", "--fps", "100", "--seconds", "120",
                                   "--no-progress", "--serve", "--http", "127.0.0.1:0", "--cpus", "share",
                                   "--out", str(out)], tmp_path)
    try:
        def running() -> bool:
            d2 = rec / "part-0001" / "data2d_distorted.bin"  # frames received and flushed: the trigger runs
            kids = descendants(demo.pid).values()
            return (d2.exists() and d2.stat().st_size > 0
                    and sum(_is_edge(c) for _, c in kids) == 2
                    and sum("flytrack_host.cli demo" in c for _, c in kids) == 1)  # the simulated cameras

        demo.wait_for("recording frames", running, 180.0)
    except BaseException:
        demo.abandon()
        raise
    before, gone, t_exit = demo.stop(sig)
    rc, err = demo.proc.returncode, demo.stderr
    report("demo", sig, before, gone, t_exit, rc)
    cmds = [c for _, c in before.values()]
    assert sum(_is_edge(c) for c in cmds) == 2 and any("flytrack_host.cli demo" in c for c in cmds), cmds
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
        return
    assert rc == CTRL_C_EXIT["demo"], err[-3000:]
    assert "stopped by " + ("SIGTERM" if sig == signal.SIGTERM else "Ctrl-C") in err, err[-3000:]
    assert finalised(rec), sorted(p.name for p in rec.rglob("*"))
    d2 = load_recording(rec).table("data2d_distorted")
    assert len(d2) > 0
    info = subprocess.run(FLYTRACK + ["recording", "info", str(rec)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert info.returncode == 0, info.stdout + info.stderr


# --- flytrack run ---------------------------------------------------------------------------------
def _points(cam: int, frame: int) -> np.ndarray:
    p = np.zeros(2, POINT_DTYPE)
    p["x_dist"] = 100.0 + cam + frame * 0.5
    p["y_dist"] = 200.0 + frame * 0.25
    p["x_undist"], p["y_undist"] = p["x_dist"], p["y_dist"]
    p["area"] = 4.0
    p["orientation"] = p["eccentricity"] = np.nan
    return p


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_run_stops_with_everything_it_started_and_finalises(tmp_path, sig):
    """`flytrack run` (software trigger, two cameras fed over UDP by this test) signalled while it
    records: whatever it started is gone (it starts no process today: the check holds the next one
    to it); after SIGINT or SIGTERM its recording is finalised with the frames sent, and it exits as on
    Ctrl-C (0)."""
    rig = tmp_path / "rig.toml"
    rig.write_text(
        'name = "stoptest"\n[trigger]\nkind = "software"\nfps = 100.0\n'
        '[host]\nlisten = "127.0.0.1:7000"\n'
        '[recording]\nfolder = "rec"\nflush_interval_s = 0.5\n'
        '[[cameras]]\nname = "a"\nindex = 0\nedge = "127.0.0.1"\n'
        '[[cameras]]\nname = "b"\nindex = 1\nedge = "127.0.0.1"\n'
    )
    out = tmp_path / "run.flytrack"
    run = Command(FLYTRACK[1:] + ["run", str(rig), "--bind", "127.0.0.1:0", "--recording", str(out),
                                  "--http", "127.0.0.1:0"], tmp_path)
    try:
        run.wait_for("listening", lambda: "listening on" in run.stdout, 120.0)
        line = next(ln for ln in run.stdout.splitlines() if ln.startswith("listening on"))
        port = int(line.split()[2].rstrip(";").rsplit(":", 1)[1])
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            seq = [0, 0]
            for k in range(50):  # half a second of frames, paced
                for cam in (0, 1):
                    ff = FeatureFrame(camera_index=cam, seq=seq[cam], camera_frame=k, trigger_frame=k,
                                      total_points=2, points=_points(cam, k))
                    for d in encode_features(ff):
                        sock.sendto(d, ("127.0.0.1", port))
                    seq[cam] += 1
                time.sleep(0.01)
        d2 = out / "part-0001" / "data2d_distorted.bin"
        run.wait_for("recording frames", lambda: d2.exists() and d2.stat().st_size > 0, 60.0)
    except BaseException:
        run.abandon()
        raise
    before, gone, t_exit = run.stop(sig)
    rc, err = run.proc.returncode, run.stderr
    report("run", sig, before, gone, t_exit, rc)
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
        return
    assert rc == CTRL_C_EXIT["run"], err[-3000:]
    assert finalised(out), sorted(p.name for p in out.rglob("*"))
    d2 = load_recording(out).table("data2d_distorted")
    assert {int(c) for c in d2["camera_index"]} == {0, 1}


# --- the fault suite ------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=lambda s: signal.Signals(s).name)
def test_fault_suite_leaves_no_process(tmp_path, sig):
    """`python -m flytrack_host.sim.faults --only restart` signalled once the scenario's edge was
    restarted (a `flytrack-edge` started from the fault's own short-lived thread): its scenario process,
    that one's edges, simulated cameras and the restarted edge all end with it. The run is made long
    (120 s) so that none of them can end on its own within the deadline."""
    suite = Command(["-m", "flytrack_host.sim.faults", "--only", "restart", "--jobs", "1", "--seconds", "120"],
                    tmp_path, TMPDIR=str(tmp_path))
    try:
        def restarted() -> bool:
            if not list(tmp_path.glob("flytrack-faults-*/restart/edge_restarted.log")):
                return False
            kids = descendants(suite.pid).values()
            return sum(_is_edge(c) for _, c in kids) == 3  # two first edges and the restarted one

        suite.wait_for("the restarted edge running", restarted, 180.0)
    except BaseException:
        suite.abandon()
        raise
    before, gone, t_exit = suite.stop(sig)
    report("fault suite", sig, before, gone, t_exit, suite.proc.returncode)
    cmds = [c for _, c in before.values()]
    assert any("flytrack_host.sim.faults one restart" in c for c in cmds), cmds
    assert sum(_is_edge(c) for c in cmds) == 3, cmds
    assert suite.proc.returncode == -sig


# --- the live page's browser (tests and `web.bench --browser`) ---------------------------------------
def test_browser_ends_with_the_process_that_started_it(tmp_path):
    """live.web.browser.Browser (chromedriver, chromium and chromium's helpers) in a process SIGKILLed
    while the page is open: none of them is left."""
    from flytrack_host.live.web import browser

    why = browser.missing()
    if why:
        pytest.fail(why)
    page = tmp_path / "page.html"
    page.write_text("<p id=p>ready</p>")
    holder = Command(["-c", "import time\nfrom flytrack_host.live.web import browser\nb = browser.Browser()\n"
                      f"b.driver.get({page.as_uri()!r})\n"
                      "print(b.js(\"return document.getElementById('p').textContent\"), flush=True)\n"
                      "time.sleep(3600)\n"], tmp_path)  # until killed
    try:
        holder.wait_for("the page open", lambda: "ready" in holder.stdout, 120.0)
    except BaseException:
        holder.abandon()
        raise
    before, gone, t_exit = holder.stop(signal.SIGKILL)
    report("browser holder", signal.SIGKILL, before, gone, t_exit, holder.proc.returncode)
    programs = [c.split()[0] for _, c in before.values() if c]  # (a chromium helper may show no command line)
    assert any(p.endswith("/chromedriver") for p in programs), programs
    assert sum(p.endswith("/chromium") for p in programs) >= 2, programs  # the browser and its helpers

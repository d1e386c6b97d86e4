"""util.children: a child started through it ends with the process that started it, whatever ends that
one; not with the thread that asked for it; and otherwise it is the subprocess call it replaces.

Each case runs a small parent script in a process of its own, which the test then SIGKILLs; every
wait is for a condition, with a deadline."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from flytrack_host.util import children

DEADLINE_S = 10.0


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in "ZX"


def _parent(script: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(script)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _read_pid(parent: subprocess.Popen) -> int:
    line = parent.stdout.readline()  # the script prints it, or ends (EOF)
    assert line.startswith("child "), (line, parent.stderr.read() if parent.poll() is not None else "")
    return int(line.split()[1])


def _gone_after_parent_killed(parent: subprocess.Popen, pid: int) -> float:
    """SIGKILL the parent; seconds until the child `pid` is gone (fails after DEADLINE_S)."""
    assert _alive(pid)
    t0 = time.monotonic()
    parent.kill()
    parent.wait()
    while _alive(pid):
        if time.monotonic() - t0 > DEADLINE_S:
            os.kill(pid, signal.SIGKILL)
            raise AssertionError(f"child {pid} still running {DEADLINE_S:.0f} s after its parent was killed")
        time.sleep(0.002)
    return time.monotonic() - t0


def test_a_program_ends_with_its_parent_not_with_the_thread_that_started_it():
    """popen from a thread that then ends: the program still answers (it did not get the death signal
    with that thread), and it ends when its process is SIGKILLed."""
    parent = _parent("""
        import os, subprocess, sys, threading, time
        from flytrack_host.util import children
        box = []
        echo = ("import sys, time\\nprint('running', flush=True)\\nprint(sys.stdin.readline().strip(), flush=True)\\n"
                "time.sleep(3600)")

        def start():  # the thread lasts until the program runs (its death signal is set by then)
            p = children.popen([sys.executable, "-c", echo], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert p.stdout.readline() == "running\\n"
            box.append(p)

        t = threading.Thread(target=start)
        t.start()
        t.join()
        while os.path.exists(f"/proc/self/task/{t.native_id}"):  # the thread is gone, for the kernel too
            time.sleep(0.001)
        p = box[0]
        try:
            p.stdin.write("still here\\n")
            p.stdin.flush()
            answer = p.stdout.readline().strip() or "(killed)"
        except BrokenPipeError:
            answer = "(killed)"
        print("child", p.pid, answer, flush=True)
        sys.stdin.read()
    """)
    try:
        line = parent.stdout.readline()
        assert line.split()[2:] == ["still", "here"], (line, parent.stderr.read() if parent.poll() is not None else "")
        dt = _gone_after_parent_killed(parent, int(line.split()[1]))
    finally:
        parent.kill()
        parent.wait()
    print(f"\nchild gone {dt * 1e3:.1f} ms after its parent was SIGKILLed")


@pytest.mark.parametrize("where", ["main thread", "other thread"])
def test_a_forked_child_ends_with_its_parent(where):
    """A multiprocessing "fork" child run through tied(): the death signal (started from the main thread)
    or the watchdog on the parent pid (from another thread) ends it when its parent is SIGKILLed."""
    parent = _parent(f"""
        import multiprocessing as mp, sys, threading, time
        from flytrack_host.util.children import tied
        def forever():
            while True:
                time.sleep(1)
        procs = []
        def start():
            p = mp.get_context("fork").Process(target=tied(forever), daemon=True)
            p.start()
            procs.append(p)
        if {where!r} == "main thread":
            start()
        else:
            t = threading.Thread(target=start)
            t.start()
            t.join()
        print("child", procs[0].pid, flush=True)
        sys.stdin.read()
    """)
    try:
        pid = _read_pid(parent)
        dt = _gone_after_parent_killed(parent, pid)
    finally:
        parent.kill()
        parent.wait()
    print(f"\n{where}: forked child gone {dt * 1e3:.1f} ms after its parent was SIGKILLed")


def test_run_is_subprocess_run():
    r = children.run([sys.executable, "-c", "import sys; print(sys.stdin.read().upper()); sys.exit(3)"],
                     input="abc", capture_output=True, text=True)
    assert (r.returncode, r.stdout.strip()) == (3, "ABC")
    assert r.args[0] == sys.executable
    with pytest.raises(subprocess.CalledProcessError):
        children.run([sys.executable, "-c", "raise SystemExit(2)"], check=True)
    with pytest.raises(subprocess.TimeoutExpired):
        children.run([sys.executable, "-c", "import time; time.sleep(60)"], timeout=0.5)
    with pytest.raises(FileNotFoundError):
        children.popen(["flytrack-no-such-program"])


def test_the_program_gets_default_signal_dispositions_and_the_same_pid():
    """The wrapper is Python, which ignores SIGPIPE and SIGXFSZ: the program must not inherit that
    (a `flytrack-edge` writing into a closed pipe must end as it does when subprocess starts it)."""
    plain = subprocess.run(["grep", "SigIgn", "/proc/self/status"], capture_output=True, text=True)
    wrapped = children.run(["grep", "SigIgn", "/proc/self/status"], capture_output=True, text=True)
    assert wrapped.stdout == plain.stdout
    p = children.popen(["sh", "-c", "echo $$"], stdout=subprocess.PIPE, text=True)
    assert int(p.communicate()[0]) == p.pid  # exec'd in place: Popen.pid is the program's

"""Child processes that end with the process that started them, whatever signal ends it.

A FlyTrack command starts processes of its own (the demo's `flytrack-edge` per camera, the simulated
cameras, the trigger firmware in simavr, a Modbus server, a fault suite's runs). When that command
ends by SIGTERM (a service manager, a supervisor) or SIGKILL, no `finally` runs: without help its
children would run on, orphaned, for good. Two ways here make them end with it:

- a program started with `popen` / `run` (instead of `subprocess.Popen` / `subprocess.run`) starts
  through a tiny exec wrapper (`python -I -S -c WRAPPER`, ~15 ms) that sets the Linux parent-death
  signal, `prctl(PR_SET_PDEATHSIG, SIGKILL)`, checks that its parent is still the one that started it
  (it may have ended before the signal was set), and then execs the program: same pid, same pipes,
  same environment. The wrapper, not a `preexec_fn`, because a `preexec_fn` runs Python between fork
  and exec, which may deadlock in a process with threads. The death signal survives the exec (not of
  set-user-ID programs, which FlyTrack does not start).
- a forked child (multiprocessing's "fork" context) runs its target through `tied(target)`: first
  thing in the child it sets the same death signal, and a watchdog thread polls the parent's pid (a
  process whose parent ended is given to another: its getppid changes) as a backstop.

The death signal fires when the *thread* that forked the child ends, not the process. A child started
from the main thread is safe (the main thread lasts as long as the process); `popen` called from any
other thread hands the fork to one long-lived daemon thread of this module (`flytrack-spawner`), so a
child of a short-lived thread (a fault injector, a suite's worker) does not die with that thread.

This process's own handling of SIGTERM (as Ctrl-C) is `util.stopping`.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import queue
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
WATCHDOG_POLL_S = 0.2  # how often a forked child's watchdog looks at its parent's pid

# Run as `python -I -S -c WRAPPER PARENT_PID SIGNAL PROGRAM ARGV0 ARGS...`. Self-contained (isolated
# mode, no site: no FlyTrack import, nothing from the environment): set the death signal, make sure
# the parent is still there, give back the signal dispositions Python changed at its start-up
# (SIGPIPE, SIGXFSZ ignored; as subprocess's restore_signals does), exec.
WRAPPER = r"""
import ctypes, os, signal, sys
parent, sig, prog = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if ctypes.CDLL(None, use_errno=True).prctl(1, sig, 0, 0, 0) != 0:
    os.write(2, b"flytrack child wrapper: prctl(PR_SET_PDEATHSIG) failed\n")
    os._exit(126)
if os.getppid() != parent:
    os._exit(125)
for s in (signal.SIGPIPE, signal.SIGXFSZ):
    signal.signal(s, signal.SIG_DFL)
try:
    os.execv(prog, sys.argv[4:])
except OSError as exc:
    os.write(2, ("flytrack child wrapper: cannot run %s: %s\n" % (prog, exc)).encode())
    os._exit(127)
"""


def command(argv: Sequence[str | os.PathLike], sig: int = signal.SIGKILL, env: dict[str, str] | None = None,
            cwd: str | os.PathLike | None = None) -> list[str]:
    """`argv` as a command line whose program gets `sig` when this process's current thread ends
    (see the module docstring; `popen` uses it and also takes care of that thread).

    The program is looked up here, as subprocess.Popen would (PATH of `env`, or of this process; a
    relative path from `cwd`): a missing program raises FileNotFoundError here, as Popen would."""
    args = [os.fspath(a) for a in argv]
    if not args:
        raise ValueError("an empty command")
    return [sys.executable, "-I", "-S", "-c", WRAPPER, str(os.getpid()), str(int(sig)),
            _find(args[0], env, cwd), *args]


def _find(prog: str, env: dict[str, str] | None = None, cwd: str | os.PathLike | None = None) -> str:
    """The absolute path of the program `prog`, as subprocess.Popen would find it; FileNotFoundError."""
    if os.sep in prog:
        path = prog if os.path.isabs(prog) or cwd is None else os.path.join(os.fspath(cwd), prog)
        found = path if os.path.isfile(path) and os.access(path, os.X_OK) else None
    else:
        search = (env if env is not None else os.environ).get("PATH", os.defpath)
        found = shutil.which(prog, path=search)
    if found is None:
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", prog)
    return os.path.abspath(found)


def script(path: str | os.PathLike, program: str | os.PathLike, sig: int = signal.SIGKILL) -> Path:
    """An executable shell script at `path` that runs `program` (with the script's arguments) tied to the
    process that runs the script, for a program that a library starts on its own (selenium starts
    chromedriver, which starts chromium): hand the library the script instead of the program."""
    p = Path(path)
    found = _find(os.fspath(program))  # looked up now: a missing program fails here, not in the library
    p.write_text("#!/bin/sh\n# util.children: the program ends with the process that started it\n"
                 f"exec {shlex.quote(sys.executable)} -I -S -c {shlex.quote(WRAPPER)} \"$PPID\" {int(sig)} "
                 f"{shlex.quote(found)} {shlex.quote(found)} \"$@\"\n")
    p.chmod(0o755)
    return p


T = TypeVar("T")


class _Spawner:
    """One daemon thread that lives as long as the process and runs the forks asked of it from other
    threads (a child's death signal follows the thread that forked it)."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[tuple[Callable[[], Any], list, threading.Event]] = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._run, name="flytrack-spawner", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            fn, box, done = self._q.get()
            try:
                box.append((True, fn()))
            except BaseException as exc:  # handed back to the caller's thread
                box.append((False, exc))
            done.set()

    def call(self, fn: Callable[[], T]) -> T:
        box: list[tuple[bool, Any]] = []
        done = threading.Event()
        self._q.put((fn, box, done))
        done.wait()
        ok, value = box[0]
        if not ok:
            raise value
        return value


_spawner: _Spawner | None = None
_spawner_lock = threading.Lock()


def _on_long_lived_thread(fn: Callable[[], T]) -> T:
    """fn() on the main thread when called there, else on the spawner thread."""
    global _spawner
    if threading.current_thread() is threading.main_thread():
        return fn()
    with _spawner_lock:
        if _spawner is None or not _spawner.thread.is_alive():
            _spawner = _Spawner()
    return _spawner.call(fn)


def _forget_spawner_after_fork() -> None:
    global _spawner, _spawner_lock
    _spawner = None  # its thread is not in the child
    _spawner_lock = threading.Lock()


os.register_at_fork(after_in_child=_forget_spawner_after_fork)


def popen(argv: Sequence[str | os.PathLike], *, death_signal: int = signal.SIGKILL, **kwargs: Any) -> subprocess.Popen:
    """subprocess.Popen(argv, **kwargs) whose child ends (`death_signal`) when this process ends, by
    whatever signal. Not for shell=True or executable=. `Popen.args` is the wrapped command line."""
    if kwargs.get("shell") or kwargs.get("executable") is not None:
        raise ValueError("children.popen runs a program, not a shell line nor another executable")
    if kwargs.get("preexec_fn") is not None:
        raise ValueError("children.popen: no preexec_fn (not fork-safe; the wrapper sets what is needed)")
    cmd = command(argv, death_signal, env=kwargs.get("env"), cwd=kwargs.get("cwd"))
    return _on_long_lived_thread(lambda: subprocess.Popen(cmd, **kwargs))


def run(argv: Sequence[str | os.PathLike], *, input: Any = None, capture_output: bool = False,  # noqa: A002
        timeout: float | None = None, check: bool = False, death_signal: int = signal.SIGKILL,
        **kwargs: Any) -> subprocess.CompletedProcess:
    """subprocess.run with the child started by `popen` (it ends with this process); same arguments,
    same result and errors (CompletedProcess.args is `argv`)."""
    if capture_output:
        kwargs["stdout"] = kwargs["stderr"] = subprocess.PIPE
    if input is not None:
        kwargs["stdin"] = subprocess.PIPE
    args = [os.fspath(a) for a in argv]
    with popen(args, death_signal=death_signal, **kwargs) as p:
        try:
            out, err = p.communicate(input, timeout=timeout)
        except subprocess.TimeoutExpired as exc:
            p.kill()
            exc.stdout, exc.stderr = p.communicate()
            exc.cmd = args
            raise
        except BaseException:
            p.kill()
            raise
        rc = p.poll()
    if check and rc:
        raise subprocess.CalledProcessError(rc, args, out, err)
    return subprocess.CompletedProcess(args, rc if rc is not None else -1, out, err)


def die_with_parent(parent_pid: int, sig: int = signal.SIGKILL, pdeathsig: bool = True,
                    poll_s: float = WATCHDOG_POLL_S) -> None:
    """In a forked child, first thing: end (`sig` to itself) when `parent_pid` (the pid of the process
    that forked it, taken before the fork) ends. `pdeathsig`: also the kernel's parent-death signal,
    right only when the forking thread lasts as long as its process (see the module docstring); the
    watchdog thread, polling every `poll_s`, does not depend on it. SIGTERM goes back to its default
    (a child does not inherit its parent's "SIGTERM as Ctrl-C", util.stopping)."""
    if pdeathsig:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    with contextlib.suppress(ValueError):  # not this process's main thread: leave it
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os.kill(os.getpid(), sig)

    threading.Thread(target=watch, name="flytrack-parent-watch", daemon=True).start()


def _run_tied(parent: int, from_main: bool, sig: int, target: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    die_with_parent(parent, sig, pdeathsig=from_main)
    return target(*args, **kwargs)


def tied(target: Callable[..., Any], sig: int = signal.SIGKILL) -> Callable[..., Any]:
    """`target` for a multiprocessing Process, made to end with this process: `ctx.Process(target=tied(fn),
    args=...)` (any start method: it pickles when `target` does). Create it in the thread that starts
    the process."""
    return functools.partial(_run_tied, os.getpid(), threading.current_thread() is threading.main_thread(),
                             int(sig), target)


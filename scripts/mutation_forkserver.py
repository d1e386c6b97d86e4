"""Fork server for `make mutation`: runs pytest for each mutant in a forked child of a process that
has already imported what the tests need, except the mutated module and what imports it.

A mutant's test run is mostly interpreter start-up and imports (NumPy, SciPy, pytest, the package:
about 2 s of a 2.5 s run on the loaded build machine); the tests themselves take a fraction of that.
The server imports those modules once; each run forks it, so every run starts from the same clean
state, as a fresh process would, and the mutated file is read from disk in the child.

    serve SOCKET TARGET MODULES_FILE   (TARGET: dotted module or package that is mutated)
    run SOCKET PYTEST_ARGS...          (the runner mutmut calls: exit status = pytest's)

Which modules to preload is recorded by one normal run of the same tests (`record OUT PYTEST_ARGS`).
A module that imports the target (directly or not) fails to import in the server, where the target
is blocked, and is imported fresh in every child. If the server is gone the client exits with 3,
which mutmut counts as a surviving mutant: a broken server can lower the kill rate, never raise it.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import sys


def _client(sock_path: str, args: list[str]) -> int:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(sock_path)
        socket.send_fds(s, [json.dumps({"cwd": os.getcwd(), "args": args}).encode()], [0, 1, 2])
        reply = b""
        while chunk := s.recv(64):
            reply += chunk
    except OSError as e:
        print(f"mutation fork server unreachable: {e}", file=sys.stderr)
        return 3
    if not reply:
        return 3
    rc = int(reply)
    if rc < 0:  # the child died of a signal: die of it too, as a plain pytest process would have
        os.kill(os.getpid(), -rc)
    return rc


def _record(out: str, args: list[str]) -> int:
    import pytest

    rc = pytest.main(args)
    with open(out, "w") as f:
        json.dump(sorted(sys.modules), f)
    return int(rc)


class _Block:
    """Meta-path finder refusing the target module (and its submodules) in the server."""

    def __init__(self, target: str):
        self.target = target

    def find_spec(self, name, path=None, target=None):  # noqa: ANN001
        if name == self.target or name.startswith(self.target + "."):
            raise ImportError(f"{name} is imported fresh in each run")
        return None


def _serve(sock_path: str, target: str, modules_file: str) -> int:
    import importlib

    with open(modules_file) as f:
        names = json.load(f)
    block = _Block(target)
    sys.meta_path.insert(0, block)
    preloaded = 0
    for name in names:
        last = name.split(".")[-1]
        if name == "__main__" or last.startswith("test_") or last == "conftest" or name.startswith(("tests", "host")):
            continue
        try:
            importlib.import_module(name)
            preloaded += 1
        except BaseException:  # noqa: BLE001 - any module that cannot load here loads in the child
            pass
    sys.meta_path.remove(block)
    for name in [n for n in sys.modules if n == target or n.startswith(target + ".")]:
        del sys.modules[name]
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(sock_path)
    srv.listen(4)
    print(f"mutation fork server: {preloaded} modules preloaded", file=sys.stderr, flush=True)
    import pytest

    while True:
        conn, _ = srv.accept()
        try:
            msg, fds, _, _ = socket.recv_fds(conn, 1 << 16, 3)
            req = json.loads(msg)
        except (OSError, ValueError):
            conn.close()
            continue
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            srv.close()
            conn.close()
            os.setsid()
            for k, fd in enumerate(fds):
                os.dup2(fd, k)
                os.close(fd)
            os.chdir(req["cwd"])
            sys.path[0] = req["cwd"]  # as `python -m pytest` would
            sys.argv = ["pytest", *req["args"]]
            try:
                rc = int(pytest.main(req["args"]))
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 1
            except BaseException:  # noqa: BLE001
                rc = 3
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(rc)
        for fd in fds:
            os.close(fd)
        while True:  # wait for the child; kill it if mutmut killed the client (its timeout)
            readable, _, _ = select.select([conn], [], [], 0.05)
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                try:
                    conn.sendall(str(os.waitstatus_to_exitcode(status)).encode())
                except OSError:
                    pass
                break
            if readable and not conn.recv(1):
                os.killpg(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                break
        conn.close()


def main() -> int:
    mode, rest = sys.argv[1], sys.argv[2:]
    if mode == "run":
        return _client(rest[0], rest[1:])
    if mode == "record":
        return _record(rest[0], rest[1:])
    if mode == "serve":
        return _serve(*rest[:3])
    print(f"usage: {sys.argv[0]} serve|run|record ...", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

"""Fixtures for flytrack-edge tests: the built daemon, a UDP receiver, a control sender."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import pytest

from flytrack_host.protocol import decode_datagram

REPO = Path(__file__).resolve().parents[2]


# The sanitizer build must stop at its first finding (exit status != 0 and the report on stderr);
# leaks count as findings too. Harmless for the plain build, which ignores these variables.
SANITIZER_ENV = {
    "ASAN_OPTIONS": "abort_on_error=1:detect_leaks=1:halt_on_error=1",
    "UBSAN_OPTIONS": "halt_on_error=1:print_stacktrace=1",
}
SANITIZER_REPORTS = ("ERROR: AddressSanitizer", "ERROR: LeakSanitizer", "runtime error:")


def edge_binary(name: str = "flytrack-edge") -> Path:
    build = Path(os.environ.get("FLYTRACK_BUILD_DIR", REPO / "build"))
    path = build / "edge" / "feature_extractor" / name
    if not path.is_file():
        pytest.fail(f"{path} is missing: run `make cbuild` first")
    return path


@pytest.fixture(autouse=True)
def _sanitizer_env(monkeypatch) -> None:
    """Every daemon started by these tests inherits the sanitizer options."""
    for k, v in SANITIZER_ENV.items():
        monkeypatch.setenv(k, v)


def _assert_clean(stderr: str) -> None:
    for r in SANITIZER_REPORTS:
        assert r not in stderr, stderr[-4000:]


@pytest.fixture
def no_sanitizer_report():
    """assert_clean(stderr): fails with the report when a sanitizer found something."""
    return _assert_clean


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class Receiver:
    """The host side: a UDP socket that collects decoded datagrams."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.messages: list = []
        self.edge_addr: tuple[str, int] | None = None

    def poll(self, timeout: float) -> list:
        """Receives for up to `timeout` s (returns as soon as one datagram came, after draining)."""
        got = []
        self.sock.settimeout(timeout)
        try:
            while True:
                data, addr = self.sock.recvfrom(65536)
                self.edge_addr = addr
                got.append(decode_datagram(data))
                self.sock.settimeout(0.0005)
        except (TimeoutError, BlockingIOError):
            pass
        self.messages.extend(got)
        return got

    def wait_for(self, pred, timeout: float = 5.0) -> list:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.poll(0.05)
            hits = [m for m in self.messages if pred(m)]
            if hits:
                return hits
        return []

    def send(self, data: bytes, port: int) -> None:
        self.sock.sendto(data, ("127.0.0.1", port))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def receiver():
    r = Receiver()
    yield r
    r.close()


@pytest.fixture
def edge_bin() -> Path:
    return edge_binary()


@pytest.fixture(params=["flytrack-edge", "flytrack-edge-san"], ids=["plain", "asan"])
def edge_any(request) -> Path:
    """The daemon, plain and built with ASan + UBSan: bad-input tests run against both."""
    return edge_binary(request.param)

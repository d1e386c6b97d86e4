"""Test helpers shared by tests/ and host/tests/: a part that should have been built is missing; a small
real file system to fill; the circles of a dependency graph (the layering tests, Python and C).

`make test` builds the C libraries, the tracker kernel, the firmware and the simavr harness, and
installs the AVR tools, before pytest runs; the Makefile exports FLYTRACK_BUILD_DIR. Under make a
missing part is therefore a broken build and fails the test; a developer running bare pytest without
a build gets a skip that names the part and how to build it.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn, TypeVar

import pytest

BUILD_ENV = "FLYTRACK_BUILD_DIR"


def under_make() -> bool:
    """True when the tests run under make (which builds every part first)."""
    return bool(os.environ.get(BUILD_ENV))


def missing_part(reason: str) -> NoReturn:
    """A built part the test needs is missing: fail under make, skip in a bare pytest run."""
    if under_make():
        pytest.fail(f"{reason} ({BUILD_ENV} is set, so make should have built it: the build is broken)",
                    pytrace=False)
    pytest.skip(f"{reason} (run `make build`, or `make test`, to build it)")


@contextmanager
def small_tmpfs(mountpoint: Path, size: str) -> Iterator[Path]:
    """A tmpfs of `size` (e.g. "4m") mounted at `mountpoint` (created) for a disk-full test, unmounted
    afterwards. Mounting needs root: the test is skipped with the reason otherwise."""
    mountpoint.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mountpoint)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mountpoint
    finally:
        subprocess.run(["umount", "-l", str(mountpoint)], check=False)


T = TypeVar("T")


def strongly_connected(graph: Mapping[T, Iterable[T]]) -> list[list[T]]:
    """The strongly connected components of more than one node (nodes that all reach each other: an
    import or call circle), each sorted; Tarjan's algorithm, iterative (no recursion limit). Nodes only
    pointed at are not in the graph's keys and count as leaves."""
    index: dict[T, int] = {}
    low: dict[T, int] = {}
    stack: list[T] = []
    on_stack: set[T] = set()
    out: list[list[T]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in graph:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp: list[T] = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out

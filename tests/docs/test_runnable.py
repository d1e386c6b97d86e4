"""The manual's commands, run as written.

A shell block in docs/ preceded by `<!-- runnable -->` is run by this test: every runnable block of a
page in order, in one temporary folder (a reader's working folder: `examples` and `build` there lead to
the repository's), with `.venv/bin` on the PATH as after `source .venv/bin/activate`. Each block must
exit with 0. The marker may carry `expect="TEXT"` (repeatable): TEXT must be in what the block printed
and, when the page shows that output in a ```text block right after, in the page too; and `timeout=S`.

In the tutorials and how-to guides every shell block is marked: `<!-- runnable ... -->`, or
`<!-- not-runnable: WHY -->` for what needs hardware or a person (a board on a USB port, a browser).
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
MARKED_DIRS = ("tutorials", "how-to")
SHELL_LANGS = ("sh", "bash", "shell", "console")
MARKER = re.compile(r"<!--\s*(runnable|not-runnable)\b(.*?)-->", re.S)


@dataclass
class Block:
    page: Path
    line: int
    code: str
    runnable: bool
    expect: list[str] = field(default_factory=list)
    timeout: float = 120.0
    shown: str | None = None  # the ```text block right after, if any


def _fences(lines: list[str]) -> list[tuple[int, int, str]]:
    """(first line, last line, language) of every fenced block."""
    out, start, lang = [], None, ""
    for i, line in enumerate(lines):
        s = line.strip()
        if s.startswith("```"):
            if start is None:
                start, lang = i, s[3:].strip().split()[0] if s[3:].strip() else ""
            else:
                out.append((start, i, lang))
                start = None
    return out


def blocks(page: Path) -> list[Block]:
    lines = page.read_text().splitlines()
    fences = _fences(lines)
    out = []
    for k, (a, b, lang) in enumerate(fences):
        if lang not in SHELL_LANGS:
            continue
        j = a - 1
        while j >= 0 and not lines[j].strip():
            j -= 1
        m = MARKER.fullmatch(lines[j].strip()) if j >= 0 else None
        if m is None and j >= 0 and lines[j].strip().endswith("-->"):   # a marker over several lines
            start = max(i for i in range(j + 1) if "<!--" in lines[i])
            m = MARKER.fullmatch(" ".join(x.strip() for x in lines[start:j + 1]))
        blk = Block(page, a + 1, "\n".join(lines[a + 1:b]), runnable=bool(m and m.group(1) == "runnable"))
        if m is None:
            blk.runnable = None  # unmarked
        elif blk.runnable:
            attrs = m.group(2)
            blk.expect = re.findall(r'expect="([^"]*)"', attrs)
            t = re.search(r"timeout=(\d+(?:\.\d+)?)", attrs)
            blk.timeout = float(t.group(1)) if t else blk.timeout
        if k + 1 < len(fences) and fences[k + 1][2] == "text" and \
                all(not x.strip() for x in lines[b + 1:fences[k + 1][0]]):
            n = fences[k + 1]
            blk.shown = "\n".join(lines[n[0] + 1:n[1]])
        out.append(blk)
    return out


def _pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


RUNNABLE_PAGES = [p for p in _pages() if any(b.runnable for b in blocks(p))]


def _flat(text: str) -> str:
    return " ".join(text.split())


def test_every_shell_block_of_the_tutorials_and_how_tos_is_marked():
    unmarked = [f"{b.page.relative_to(REPO)}:{b.line}" for p in _pages()
                if p.relative_to(DOCS).parts[0] in MARKED_DIRS for b in blocks(p) if b.runnable is None]
    assert not unmarked, ("shell blocks with neither <!-- runnable --> nor <!-- not-runnable: WHY --> before "
                          f"them: {unmarked}")


def test_the_demo_tutorial_is_runnable():
    assert DOCS / "tutorials" / "demo.md" in RUNNABLE_PAGES


def test_what_a_page_checks_is_what_it_shows():
    """An expected line must be in the output the page shows, when it shows one."""
    problems = [f"{b.page.relative_to(REPO)}:{b.line}: {e!r} is not in the output shown"
                for p in RUNNABLE_PAGES for b in blocks(p) if b.runnable and b.shown is not None
                for e in b.expect if _flat(e) not in _flat(b.shown)]
    assert not problems, "\n".join(problems)


@pytest.mark.slow
@pytest.mark.parametrize("page", RUNNABLE_PAGES, ids=[str(p.relative_to(DOCS)) for p in RUNNABLE_PAGES])
def test_the_page_runs_as_written(page: Path, tmp_path: Path):
    for name in ("examples", "build"):
        (tmp_path / name).symlink_to(REPO / name)
    env = dict(os.environ)
    env.update(PATH=f"{REPO / '.venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(REPO / ".venv"),
               COLUMNS="100", NO_COLOR="1", TERM="dumb", FLYTRACK_BUILD_DIR=str(REPO / "build"))
    groups: list[int] = []  # each block's process group: what it left in the background dies at the end
    try:
        for b in [b for b in blocks(page) if b.runnable]:
            _run(b, tmp_path, env, groups)
    finally:
        for pgid in groups:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _run(b: Block, cwd: Path, env: dict[str, str], groups: list[int]) -> None:
    where = f"{b.page.relative_to(REPO)}:{b.line}"
    proc = subprocess.Popen(["bash", "-e", "-o", "pipefail", "-c", b.code], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    groups.append(proc.pid)
    try:
        out, _ = proc.communicate(timeout=b.timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"{where}: still running after {b.timeout:g} s:\n{b.code}\n--- output:\n{out[-3000:]}")
    assert proc.returncode == 0, f"{where}: exit {proc.returncode}:\n{b.code}\n--- output:\n{out[-3000:]}"
    for e in b.expect:
        assert _flat(e) in _flat(out), f"{where}: {e!r} not in the output:\n{out[-3000:]}"


def test_the_block_parser_reads_markers_and_outputs(tmp_path: Path):
    page = tmp_path / "p.md"
    page.write_text('<!-- runnable expect="ok a" expect="b c" timeout=5 -->\n```sh\necho ok a; echo b   c\n```\n\n'
                    "```text\nok a\nb c\n```\n\n<!-- not-runnable: needs a board -->\n```sh\nflash\n```\n\n"
                    "```sh\nunmarked\n```\n")
    got = blocks(page)
    assert [(b.runnable, b.expect, b.timeout, b.shown) for b in got] == [
        (True, ["ok a", "b c"], 5.0, "ok a\nb c"), (False, [], 120.0, None), (None, [], 120.0, None)]
    assert shlex.split(got[0].code)[0] == "echo"

"""The `flytrack` command itself: help, version, rig check, run as a real subprocess."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from flytrack_host import __version__
from flytrack_host.protocol import PROTOCOL_VERSION

ROOT = Path(__file__).resolve().parents[3]


def flytrack(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "flytrack_host.cli", *args], capture_output=True, text=True, timeout=120
    )


def test_version_prints_both_versions() -> None:
    out = flytrack("version")
    assert out.returncode == 0, out.stderr
    assert f"flytrack host {__version__}" in out.stdout
    assert f"wire protocol version {PROTOCOL_VERSION}" in out.stdout


def test_help_lists_commands() -> None:
    out = flytrack("--help")
    assert out.returncode == 0, out.stderr
    for cmd in ("version", "rig"):
        assert cmd in out.stdout


def test_rig_check_ok_and_error(tmp_path: Path) -> None:
    ok = flytrack("rig", "check", str(ROOT / "examples" / "rig.toml"))
    assert ok.returncode == 0, ok.stderr
    assert "4 cameras" in ok.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text('[[cameras]]\nname = "a"\nindex = -1\n')
    out = flytrack("rig", "check", str(bad))
    assert out.returncode == 2
    assert "cameras[0].index" in out.stderr
    assert "Traceback" not in out.stderr

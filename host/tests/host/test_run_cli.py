"""`flytrack run` tells how to run without a trigger board (GitHub issue 5, D)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from flytrack_host.cli import app

ROOT = Path(__file__).resolve().parents[3]


def test_run_help_documents_no_trigger():
    r = CliRunner().invoke(app, ["run", "--help"], env={"COLUMNS": "200", "NO_COLOR": "1"})
    out = " ".join(r.output.split())
    assert r.exit_code == 0
    assert "--no-trigger" in out and "Without a trigger board, pass --no-trigger" in out


def test_run_without_the_board_says_to_use_no_trigger(tmp_path):
    rig = (ROOT / "examples" / "rig.toml").read_text()
    rig = rig.replace('folder = "recordings"', f'folder = "{tmp_path / "rec"}"')
    path = tmp_path / "rig.toml"
    path.write_text(rig)
    p = subprocess.run([sys.executable, "-m", "flytrack_host.cli", "run", str(path), "--trigger-port",
                        str(tmp_path / "no_such_tty")], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    err = " ".join(p.stderr.split())
    assert "does not exist" in err and f"flytrack run {path} --no-trigger" in err
    assert not (tmp_path / "rec").exists()  # nothing recorded
    # The example rig names an actuator but no rules file: nothing drives it, and it says so.
    assert "no rules file" in err and "hscam (trigger_pulse)" in err and "not driven" in err

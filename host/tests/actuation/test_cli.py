"""`flytrack rules check` and `flytrack run --rules`: a bad rules file is one clear line per problem and
exit 2, before anything starts or is recorded."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from flytrack_host.cli import app

ROOT = Path(__file__).resolve().parents[3]
ENV = {"COLUMNS": "200", "NO_COLOR": "1"}


def test_rules_check_ok_and_against_the_rig() -> None:
    r = CliRunner().invoke(app, ["rules", "check", str(ROOT / "examples" / "closed_loop.toml"), "--rig",
                                 str(ROOT / "examples" / "rig.toml")], env=ENV)
    assert r.exit_code == 0, r.output
    assert "ok rule 'enters_box': drives hscam, valve, stimulus_can" in r.output


def test_rules_check_names_file_rule_and_field(tmp_path: Path) -> None:
    rig = str(ROOT / "examples" / "rig.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('[[rules]]\nname = "door"\n[rules.when]\nspeed_m_s = [0, 1]\n[[rules.actions]]\n'
                   'output = "lazer"\n')
    r = CliRunner().invoke(app, ["rules", "check", str(bad), "--rig", rig], env=ENV)
    assert r.exit_code == 2
    out = " ".join(r.output.split())
    assert f"{bad}: rules[0] 'door'.actions[0].output: 'lazer' is not an actuator of the rig" in out
    # A message with brackets in it reaches the terminal whole (rich would take [x, y, z] for markup).
    bad.write_text('[[rules]]\nname = "post"\ndry_run = true\n[rules.when]\n'
                   'distance_m = { point = [0, 0, 0], post = [0, 0] }\n')
    r = CliRunner().invoke(app, ["rules", "check", str(bad)], env=ENV)
    out = " ".join(r.output.split())
    assert r.exit_code == 2
    assert f"{bad}: rules[0] 'post'.when.distance_m: give exactly one of point = [x, y, z] or post = [x, y]" in out


def test_run_with_a_bad_rules_file_exits_before_starting(tmp_path: Path) -> None:
    rig = (ROOT / "examples" / "rig.toml").read_text().replace('folder = "recordings"',
                                                               f'folder = "{tmp_path / "rec"}"')
    (tmp_path / "rig.toml").write_text(rig)
    bad = tmp_path / "rules.toml"
    bad.write_text('[[rules]]\nname = "door"\ncooldown_s = "soon"\n[rules.when]\nspeed_m_s = [0, 1]\n'
                   '[[rules.actions]]\noutput = "hscam"\n')
    p = subprocess.run([sys.executable, "-m", "flytrack_host.cli", "run", str(tmp_path / "rig.toml"), "--rules",
                        str(bad), "--no-trigger"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    err = " ".join(p.stderr.split())
    assert f"{bad}: rules[0] 'door'.cooldown_s: Input should be a valid number" in err
    assert not (tmp_path / "rec").exists()


def test_run_skip_bad_rules_goes_on_and_logs_them(tmp_path: Path) -> None:
    from flytrack_host.recording import load_recording

    rig = (ROOT / "examples" / "rig.toml").read_text()
    (tmp_path / "rig.toml").write_text(rig)
    rules = tmp_path / "rules.toml"
    rules.write_text('[[rules]]\nname = "watch"\ndry_run = true\n[rules.when]\nspeed_m_s = [0, 1]\n\n'
                     '[[rules]]\nname = "door"\n[rules.when]\nspeed_m_s = [0, 1]\n'
                     '[[rules.actions]]\noutput = "lazer"\n\n'
                     '[[rules]]\nname = "typo"\ncooldwn_s = 1\ndry_run = true\n[rules.when]\nspeed_m_s = [0, 1]\n')
    p = subprocess.run([sys.executable, "-m", "flytrack_host.cli", "run", str(tmp_path / "rig.toml"), "--rules",
                        str(rules), "--skip-bad-rules", "--no-trigger", "--seconds", "1", "--bind", "127.0.0.1:0",
                        "--recording", str(tmp_path / "rec")], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    err = " ".join(p.stderr.split())
    assert "rule left out" in err and "rules[1] 'door'.actions[0].output: 'lazer' is not an actuator" in err
    assert "rules[2] 'typo'.cooldwn_s: Extra inputs are not permitted" in err
    assert "rules: watch 0 dry, 2 rule problems" in " ".join(p.stdout.split())  # the final status line
    log = [r["message"] for r in load_recording(tmp_path / "rec").textlog if r["source"] == "actuation"]
    assert any("rules from" in m and "watch (dry run)" in m for m in log)
    assert sum("rule left out" in m for m in log) == 2

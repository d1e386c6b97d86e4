"""Issue 16, item 10: CLI errors are one clear line that names the file or the key, and exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from flytrack_host.geometry.formats import CalibrationFormatError, save_calibration
from flytrack_host.io.retrack import RetrackError, params_with
from flytrack_host.rig import RigError, load_rig, parse_rig


def flytrack(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "flytrack_host.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_rig_check_on_a_folder_is_one_line_and_exit_2(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="is a folder"):
        load_rig(tmp_path)
    out = flytrack("rig", "check", str(tmp_path))
    assert out.returncode == 2 and "Traceback" not in out.stdout + out.stderr
    assert "is a folder" in " ".join((out.stdout + out.stderr).split())  # rich wraps long lines


def test_duplicate_indices_are_reported_with_field_errors() -> None:
    data = {"cameras": [{"name": "a", "index": 0, "edge": "127.0.0.1", "bogus": 1},
                        {"name": "b", "index": 0, "edge": "127.0.0.1"}]}
    with pytest.raises(RigError) as e:
        parse_rig(data)
    text = str(e.value)
    assert "share index 0" in text and "bogus" in text
    assert text.index("share index 0") < text.index("bogus")  # the costly one first


def test_set_and_params_errors_name_the_key_and_the_file(tmp_path: Path) -> None:
    with pytest.raises(RetrackError, match="motion_noise_scale = 'abc'"):
        params_with(None, sets=["motion_noise_scale=abc"])
    bad = tmp_path / "bad.toml"
    bad.write_text("x = [\n")
    with pytest.raises(RetrackError, match=f"--params {bad}"):
        params_with(None, toml_path=bad)
    with pytest.raises(RetrackError, match="No such file"):
        params_with(None, toml_path=tmp_path / "none.toml")


def test_convert_names_its_format_option(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFormatError, match="--format flydra-xml"):
        save_calibration({}, tmp_path / "x.foo")


def test_calibrate_help_lists_every_subcommand() -> None:
    out = flytrack("--help")
    text = " ".join(out.stdout.split())
    assert "intrinsics, collect" in text, text

"""The rig file: valid files load, every bad one gets an error naming the file, the field and the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from flytrack_host.rig import RigError, load_rig

ROOT = Path(__file__).resolve().parents[3]

GOOD = """
name = "t"
[trigger]
fps = 200
[[cameras]]
name = "a"
index = 0
[[cameras]]
name = "b"
index = 1
edge = "10.1.2.3"
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_example_rig_loads() -> None:
    rig = load_rig(ROOT / "examples" / "rig.toml")
    assert len(rig.cameras) == 4
    assert rig.tracking.death_position_std_m == pytest.approx(0.01212)
    assert rig.camera_by_index(2).name == "cam3"
    assert rig.camera_by_index(9) is None


def test_defaults_and_paths(tmp_path: Path) -> None:
    rig = load_rig(write(tmp_path, GOOD))
    assert rig.trigger.fps == 200
    assert rig.cameras[0].edge == "127.0.0.1"
    assert rig.tracking.motion_noise_scale == 0.1  # Braid's default
    assert rig.recording_dir == tmp_path / "recordings"


@pytest.mark.parametrize(
    ("text", "field", "hint"),
    [
        (GOOD.replace('index = 1', 'index = 0'), "cameras", "share index 0"),
        (GOOD.replace('edge = "10.1.2.3"', 'edge = "not-an-ip"'), "cameras[1].edge", "not an IP address"),
        (GOOD.replace("fps = 200", "fps = -5"), "trigger.fps", "greater than 0"),
        (GOOD + "\n[tracking]\nmotion_noise = 2\n", "tracking.motion_noise", "check its spelling"),
        (GOOD + '\n[host]\nlisten = "7000"\n', "host.listen", "HOST:PORT"),
        (GOOD.replace('name = "a"\n', ""), "cameras[0].name", "add this field"),
        (GOOD + '\n[trigger2]\n', "trigger2", "remove it"),
    ],
)
def test_bad_fields_are_named_with_a_fix(tmp_path: Path, text: str, field: str, hint: str) -> None:
    p = write(tmp_path, text)
    with pytest.raises(RigError) as info:
        load_rig(p)
    msg = str(info.value)
    assert str(p) in msg
    assert field in msg
    assert hint in msg


def test_not_toml_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="not valid TOML"):
        load_rig(write(tmp_path, "cameras = [ oops"))
    with pytest.raises(RigError, match="file not found"):
        load_rig(tmp_path / "nope.toml")
    garbage = tmp_path / "bin.toml"
    garbage.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(RigError):
        load_rig(garbage)


def test_missing_calibration_file_is_reported(tmp_path: Path) -> None:
    p = write(tmp_path, 'calibration = "cal.xml"\n' + GOOD)
    with pytest.raises(RigError, match="cal.xml does not exist"):
        load_rig(p)
    assert load_rig(p, check_files=False).calibration_path == tmp_path / "cal.xml"

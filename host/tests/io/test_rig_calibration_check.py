"""`flytrack rig check` says loudly when the rig has no calibration or a camera is missing from it."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.geometry.formats import save_flydra_xml
from flytrack_host.tracking.synthetic import arena_cameras

ROOT = Path(__file__).resolve().parents[3]


def _flat(text: str) -> str:
    return " ".join(text.split())


def test_rig_check_reports_missing_calibration_and_cameras(tmp_path: Path) -> None:
    r = CliRunner().invoke(app, ["rig", "check", str(ROOT / "examples" / "rig.toml")])
    assert r.exit_code == 0 and "NO 3D tracking" in _flat(r.output)
    cams = arena_cameras(3)
    save_flydra_xml({f"cam{i + 1}": c for i, c in cams.items()}, tmp_path / "calibration.xml")  # cam4 missing
    rig = (ROOT / "examples" / "rig.toml").read_text().replace('# calibration = "calibration.xml"',
                                                               'calibration = "calibration.xml"')
    (tmp_path / "rig.toml").write_text(rig)
    r = CliRunner().invoke(app, ["rig", "check", str(tmp_path / "rig.toml")])
    out = _flat(r.output)
    assert r.exit_code == 0 and "camera(s) 3 (cam4) are not in the calibration" in out
    save_flydra_xml({f"cam{i + 1}": c for i, c in arena_cameras(4).items()}, tmp_path / "calibration.xml")
    r = CliRunner().invoke(app, ["rig", "check", str(tmp_path / "rig.toml")])
    assert r.exit_code == 0 and "warning" not in r.output

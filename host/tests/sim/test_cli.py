import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--cameras", "1"], "--cameras must be 2..64"),
        (["--animals", "0"], "--animals must be 1..100"),
        (["--fps", "0"], "--fps must be 1..1000"),
        (["--seconds", "0.01"], "--seconds must be 0.1..3600"),
        (["--noise", "-1"], "--noise must be 0..40"),
        (["--trigger", "usb"], "--trigger must be auto, simavr or software"),
    ],
)
def test_bad_options_are_clear_errors(args, msg, tmp_path):
    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path), *args])
    assert r.exit_code == 2
    assert msg in r.output.replace("\n", " ")


def test_demo_is_listed():
    r = CliRunner().invoke(app, ["--help"])
    assert "demo" in r.output

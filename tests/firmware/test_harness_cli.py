"""The simavr harness's command line: its usage text lists every option it takes."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[2] / "firmware" / "avr_trigger" / "harness" / "trigger_sim.c"


def test_usage_lists_every_option(built: tuple) -> None:
    harness, _ = built
    table = SOURCE.read_text().split("static const struct option opts[]", 1)[1].split("};", 1)[0]
    options = re.findall(r'\{"([a-z-]+)",', table)
    assert len(options) >= 12 and "irq-log" in options
    r = subprocess.run([str(harness), "--help"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 0
    missing = [o for o in options if f"--{o}" not in r.stderr]
    assert not missing, f"usage text does not list {missing}:\n{r.stderr}"
    r = subprocess.run([str(harness), "--no-such-option"], capture_output=True, text=True, timeout=10)
    assert r.returncode == 2 and "usage:" in r.stderr and "Traceback" not in r.stderr

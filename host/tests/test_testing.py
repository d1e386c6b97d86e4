"""flytrack_host.util.testing.missing_part: a missing built part fails under make, skips in bare pytest."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from flytrack_host.util.testing import BUILD_ENV

_TEST = '''
from flytrack_host.util.testing import missing_part

def test_needs_a_part():
    missing_part("libexample not built")
'''


def _run(tmp_path: Path, build_dir: str | None) -> subprocess.CompletedProcess[str]:
    (tmp_path / "test_part.py").write_text(_TEST)
    env = {k: v for k, v in os.environ.items() if k != BUILD_ENV}
    if build_dir is not None:
        env[BUILD_ENV] = build_dir
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rfs", "-p", "no:cacheprovider", "-c", os.devnull,
                           str(tmp_path / "test_part.py")], capture_output=True, text=True, env=env, timeout=60)


def test_missing_part_fails_under_make(tmp_path: Path) -> None:
    r = _run(tmp_path, str(tmp_path))
    assert r.returncode == 1, r.stdout + r.stderr
    assert "1 failed" in r.stdout and "libexample not built" in r.stdout and BUILD_ENV in r.stdout


def test_missing_part_skips_without_a_build(tmp_path: Path) -> None:
    r = _run(tmp_path, None)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 skipped" in r.stdout and "libexample not built" in r.stdout and "make build" in r.stdout

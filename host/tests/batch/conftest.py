"""Synthetic recordings for the batch tests (2D data of known flights, with their calibration)."""

from __future__ import annotations

from pathlib import Path

import pytest

from flytrack_host.recording.synthetic import write_synthetic_recording


@pytest.fixture(scope="session")
def recordings(tmp_path_factory) -> list[Path]:
    d = tmp_path_factory.mktemp("batch-recordings")
    return [write_synthetic_recording(d / f"rec{i}.flytrack", n_cameras=4, n_targets=2, duration_s=3.0,
                                      seed=i).parent for i in range(4)]

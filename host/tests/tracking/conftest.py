"""Tests marked `c_kernel` need the C tracker kernel: under make (which builds it) its absence fails
them, in a bare pytest run without a build it skips them (flytrack_host.util.testing.missing_part)."""

from __future__ import annotations

import pytest

from flytrack_host.tracking import kernel as ckernel
from flytrack_host.util.testing import missing_part


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "c_kernel: needs the C tracker kernel (built by `make cbuild`)")


@pytest.fixture(autouse=True)
def _c_kernel_built(request: pytest.FixtureRequest) -> None:
    if request.node.get_closest_marker("c_kernel") is None:
        return
    reason = ckernel.unavailable_reason()
    if reason is not None:
        missing_part(f"C tracker kernel not built: {reason}")

"""Test helpers shared by tests/ and host/tests/: a part that should have been built is missing.

`make test` builds the C libraries, the tracker kernel, the firmware and the simavr harness, and
installs the AVR tools, before pytest runs; the Makefile exports FLYTRACK_BUILD_DIR. Under make a
missing part is therefore a broken build and fails the test; a developer running bare pytest without
a build gets a skip that names the part and how to build it.
"""

from __future__ import annotations

import os
from typing import NoReturn

import pytest

BUILD_ENV = "FLYTRACK_BUILD_DIR"


def under_make() -> bool:
    """True when the tests run under make (which builds every part first)."""
    return bool(os.environ.get(BUILD_ENV))


def missing_part(reason: str) -> NoReturn:
    """A built part the test needs is missing: fail under make, skip in a bare pytest run."""
    if under_make():
        pytest.fail(f"{reason} ({BUILD_ENV} is set, so make should have built it: the build is broken)",
                    pytrace=False)
    pytest.skip(f"{reason} (run `make build`, or `make test`, to build it)")

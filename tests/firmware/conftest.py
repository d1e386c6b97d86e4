"""Shared fixtures of the firmware-in-simavr tests: build once; without the AVR tools a skip in a bare
pytest run, a failure under make (which installs them)."""

from __future__ import annotations

import pytest

from flytrack_host.trigger import simulator
from flytrack_host.util.testing import missing_part

FIGURES: dict[str, str] = {}
DVS_FIGURES: dict[str, str] = {}


@pytest.fixture(scope="session")
def built() -> tuple:
    if not simulator.tools_available():
        missing_part("avr-gcc / simavr not installed: the firmware cannot run here (SoftwareTrigger covers the host)")
    return simulator.build("atmega328p")


@pytest.fixture
def figures() -> dict[str, str]:
    return FIGURES


@pytest.fixture
def dvs_figures() -> dict[str, str]:
    return DVS_FIGURES


def pytest_terminal_summary(terminalreporter) -> None:  # noqa: ANN001 - pytest hook
    if FIGURES:
        terminalreporter.section("trigger firmware figures (simavr)")
        for k, v in FIGURES.items():
            terminalreporter.write_line(f"{k}: {v}")
    if DVS_FIGURES:
        terminalreporter.section("DVS bridge firmware figures (simavr)")
        for k, v in DVS_FIGURES.items():
            terminalreporter.write_line(f"{k}: {v}")

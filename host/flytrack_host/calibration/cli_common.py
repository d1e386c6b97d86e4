"""The `flytrack calibrate` command group (its typer app) and what its command modules share: one
paragraph and exit code 2 for known bad input, never a traceback. cli.py and dvs_cli.py add commands.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import typer
from rich.console import Console

from flytrack_host.calibration.align import AlignError
from flytrack_host.calibration.dlt import DLTError
from flytrack_host.calibration.intrinsics import IntrinsicsError
from flytrack_host.calibration.observations import PointsFileError
from flytrack_host.calibration.selfcal import SelfCalError
from flytrack_host.geometry.formats import CalibrationFormatError

app = typer.Typer(help="Camera calibration: DLT, LED self-calibration, alignment, formats.", no_args_is_help=True)
console = Console()
err = Console(stderr=True)

_ERRORS = (CalibrationFormatError, PointsFileError, SelfCalError, AlignError, DLTError, IntrinsicsError)
F = TypeVar("F", bound=Callable[..., Any])


class InputError(ValueError):
    """Bad command-line input (a CSV that does not parse, a size that is not WxH)."""


def _clean_errors(fn: F) -> F:
    """Known bad input -> one paragraph on stderr and exit code 2, never a traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (*_ERRORS, InputError) as exc:
            err.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
            raise typer.Exit(code=2) from None

    return wrapper  # type: ignore[return-value]


def _parse_size(s: str, what: str = "image size") -> tuple[int, int]:
    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        example = "1280x1024" if what == "image size" else "9x6"
        raise InputError(f"{what} {s!r} is not two numbers AxB (e.g. {example}).") from None
    return w, h

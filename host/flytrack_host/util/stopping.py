"""SIGTERM handled as Ctrl-C: what a service manager or a supervisor sends stops a run as Ctrl-C does.

Python turns SIGINT (Ctrl-C) into KeyboardInterrupt in the main thread, and `flytrack run` and
`flytrack demo` stop cleanly on it: the trigger stops, the pipeline tracks what is pending, the
recording is finalised, the processes they started are stopped. SIGTERM, by default, ends the process
at once: none of that (its children, at least, end with it: `util.children`).

    with stopping.sigterm_as_ctrl_c():
        try:
            ...run...                      # a SIGTERM raises KeyboardInterrupt here, as Ctrl-C does
        finally:
            with stopping.shielded():
                ...finalise the recording...   # a SIGTERM here is held until the block ends

Within `sigterm_as_ctrl_c()` a SIGTERM raises KeyboardInterrupt in the main thread, so the same code
runs and the command exits with Ctrl-C's code. Cleanup that must not be cut short runs in
`shielded()`: a SIGTERM arriving then is held, and raised as KeyboardInterrupt when the block ends
normally, unless a SIGTERM already started the stop (a supervisor's repeated SIGTERM does not cut the
finalising short, nor turn a clean stop into an error). SIGINT is left as Python has it: a second
Ctrl-C still interrupts everything, the user's own choice.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType, TracebackType


class _State:
    installed = 0  # nesting depth of sigterm_as_ctrl_c
    shield = 0  # nesting depth of shielded
    held = False  # a SIGTERM came while shielded
    raised = False  # a SIGTERM was raised as KeyboardInterrupt (the stop began)
    received = 0  # SIGTERMs received while installed


_S = _State()


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    _S.received += 1
    if _S.shield:
        _S.held = True
        return
    _S.raised = True
    raise KeyboardInterrupt


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt in the main thread while the block runs (the previous handler
    is back after it). Called from another thread it does nothing (only the main thread may)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _on_sigterm)
    if not _S.installed:
        _S.held = _S.raised = False
        _S.received = 0
    _S.installed += 1
    try:
        yield
    finally:
        _S.installed -= 1
        signal.signal(signal.SIGTERM, old)


class shielded:  # noqa: N801 - used as a context manager, like contextlib's
    """A block a SIGTERM does not interrupt (see the module docstring)."""

    def __enter__(self) -> shielded:
        _S.shield += 1
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        _S.shield -= 1
        if _S.shield == 0 and _S.held:
            _S.held = False
            if exc_type is None and _S.installed and not _S.raised:
                _S.raised = True
                raise KeyboardInterrupt


def sigterm_received() -> bool:
    """Whether a SIGTERM came while `sigterm_as_ctrl_c` was in force (the last time it was entered)."""
    return _S.received > 0

"""util.stopping: SIGTERM raises KeyboardInterrupt as Ctrl-C does; a shielded block (finalising a
recording) is not cut short by it, the stop comes after it; a SIGTERM while already stopping is
dropped. Each case in a process of its own (a KeyboardInterrupt must not reach pytest)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

PRELUDE = """
import os, signal, time
from flytrack_host.util.stopping import _S, shielded, sigterm_as_ctrl_c, sigterm_received
def term():
    seen = _S.received
    os.kill(os.getpid(), signal.SIGTERM)
    end = time.monotonic() + 10
    while _S.received == seen and time.monotonic() < end:  # until the handler ran (it may raise)
        time.sleep(0.001)
    assert _S.received > seen, "the SIGTERM handler did not run"
"""

CASES = {
    # SIGTERM in the block: KeyboardInterrupt, as Ctrl-C.
    "raises": ("""
        try:
            with sigterm_as_ctrl_c():
                term()
                print("not interrupted")
        except KeyboardInterrupt:
            print("interrupted", sigterm_received())
    """, "interrupted True"),
    # SIGTERM in a shielded block: the block finishes, then KeyboardInterrupt.
    "held": ("""
        try:
            with sigterm_as_ctrl_c():
                with shielded():
                    term()
                    print("shield finished")
                print("not interrupted")
        except KeyboardInterrupt:
            print("interrupted after")
    """, "shield finished\ninterrupted after"),
    # Stopping (the first SIGTERM's KeyboardInterrupt) and a second SIGTERM in the clean-up: dropped.
    "second dropped": ("""
        with sigterm_as_ctrl_c():
            try:
                term()
            except KeyboardInterrupt:
                with shielded():
                    term()
                    print("cleaned up")
            print("exit normally")
    """, "cleaned up\nexit normally"),
    # Outside the block SIGTERM is its old self again.
    "restored": ("""
        with sigterm_as_ctrl_c():
            pass
        print(signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)
    """, "True"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_sigterm_as_ctrl_c(case):
    body, expected = CASES[case]
    r = subprocess.run([sys.executable, "-c", PRELUDE + textwrap.dedent(body)], capture_output=True, text=True,
                       timeout=60)
    assert (r.returncode, r.stdout.strip()) == (0, expected), r.stderr

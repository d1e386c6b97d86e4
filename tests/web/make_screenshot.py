"""Screenshot of the live page during a demo run, for the README (docs/live-page.png).

    .venv/bin/python tests/web/make_screenshot.py [--out docs/live-page.png] [--cameras 5] [--animals 3] \
        [--rules examples/closed_loop.toml]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

from flytrack_host.live.launch import LiveOutputs
from flytrack_host.live.web import browser as browser_mod
from flytrack_host.sim.run import DemoConfig, run_demo


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("docs/live-page.png"))
    ap.add_argument("--cameras", type=int, default=5)
    ap.add_argument("--animals", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rules", type=Path, default=None, help="closed-loop rules (examples/closed_loop.toml)")
    ap.add_argument("--at", type=float, default=0.7, help="fraction of the run at which to shoot")
    a = ap.parse_args()
    why = browser_mod.missing()
    if why:
        print(why, file=sys.stderr)
        return 2
    outputs = LiveOutputs(http=("127.0.0.1", 0))
    ready = threading.Event()

    def attach(pipe) -> None:
        outputs.attach(pipe, echo=print)
        ready.set()

    with tempfile.TemporaryDirectory() as d:
        cfg = DemoConfig(cameras=a.cameras, animals=a.animals, seconds=a.seconds, out=Path(d), progress=False,
                         attach=[attach], rules=a.rules)
        runner = threading.Thread(target=run_demo, args=(cfg,), daemon=True)
        runner.start()
        ready.wait(60)
        br = browser_mod.Browser()
        try:
            br.driver.get(outputs.server.url)
            shot = False
            while runner.is_alive() and not shot:
                f = br.js("return window.flytrack.last && window.flytrack.last.frame") or 0
                if f >= a.at * a.seconds * 100:
                    shot = True
                    a.out.parent.mkdir(parents=True, exist_ok=True)
                    br.driver.save_screenshot(str(a.out))
                    print(f"saved {a.out} at frame {f}")
                time.sleep(0.1)
            if not shot:
                print(f"no screenshot: the page never reached frame {a.at * a.seconds * 100:.0f}", file=sys.stderr)
        finally:
            br.close()
        runner.join()
    return 0


if __name__ == "__main__":
    sys.exit(main())

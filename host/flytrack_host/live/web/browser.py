"""Debian's chromium, headless, driven by selenium through Debian's chromedriver (no network): the
live page's tests and `web.bench --browser` load the page in it. Selenium is a test requirement."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--window-size=1400,1200"]


def missing() -> str | None:
    """Why the browser cannot run here, or None."""
    for p in (CHROMIUM, CHROMEDRIVER):
        if not Path(p).exists():
            return f"{p} is missing: apt-get install chromium chromium-driver (make test's set-up does)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed in .venv (host/requirements.txt pins it)"
    return None


class Browser:
    def __init__(self) -> None:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        from flytrack_host.util import children

        self.profile = tempfile.mkdtemp(prefix="flytrack-chromium-")
        # chromedriver and chromium started through util.children's scripts: chromedriver ends with this
        # process and chromium with chromedriver (its own helper processes end with it), however it ends.
        tied = Path(self.profile) / "tied"
        tied.mkdir()
        opts = webdriver.ChromeOptions()
        opts.binary_location = str(children.script(tied / "chromium", CHROMIUM))
        for f in FLAGS + [f"--user-data-dir={self.profile}"]:
            opts.add_argument(f)
        self.driver = webdriver.Chrome(service=Service(str(children.script(tied / "chromedriver", CHROMEDRIVER))),
                                       options=opts)
        self.driver.set_page_load_timeout(30)

    def js(self, script: str):
        return self.driver.execute_script(script)

    def close(self) -> None:
        try:
            self.driver.quit()
        finally:
            shutil.rmtree(self.profile, ignore_errors=True)

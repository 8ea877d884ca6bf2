"""Render an HTML page (a 3D view) to PNG in headless Chromium, and report what the page logged.

For the browser test and the committed screenshots (``benchmarks/view_screenshots.py``), and
for users who want a picture of a view for a report. Drives Debian's ``chromium`` through its
``chromedriver`` with Selenium (Apache-2.0; the ``dev`` extra). WebGL runs on SwiftShader,
Chromium's CPU renderer, so no GPU or screen is needed.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
CHROMEDRIVER_CANDIDATES = ("chromedriver",)


@dataclass(frozen=True)
class PageRender:
    """What a headless browser saw of a page.

    Attributes:
        screenshot: the PNG written.
        webgl_canvases: canvases on the page with a live WebGL context.
        errors: the browser console's SEVERE entries (JavaScript errors, failed loads).
        messages: every console entry, as text.
        seconds: wall time of the render.
    """

    screenshot: Path
    webgl_canvases: int
    errors: list[str]
    messages: list[str]
    seconds: float


def browser_available() -> str | None:
    """None when Chromium, chromedriver and Selenium are installed; else what is missing."""
    if not any(shutil.which(name) for name in CHROMIUM_CANDIDATES):
        return "no Chromium on PATH (Debian: apt-get install chromium chromium-driver)"
    if not any(shutil.which(name) for name in CHROMEDRIVER_CANDIDATES):
        return "no chromedriver on PATH (Debian: apt-get install chromium-driver)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "Selenium is not installed (pip install selenium, or the dev extra)"
    return None


def render_page(page: str | Path, screenshot: str | Path, *, width: int = 1200, height: int = 800,
                timeout_s: float = 90.0, settle_s: float = 2.0) -> PageRender:
    """Open ``page`` (a local HTML file) in headless Chromium, wait for a WebGL canvas, let the
    page draw for ``settle_s``, write a ``width`` x ``height`` PNG screenshot.

    Raises:
        RuntimeError: no browser (:func:`browser_available`), or no WebGL canvas within
            ``timeout_s`` (the console's entries are in the message).
    """
    missing = browser_available()
    if missing:
        raise RuntimeError(f"cannot render {page}: {missing}")
    from selenium import webdriver
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    start = time.perf_counter()
    options = webdriver.ChromeOptions()
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
                     # WebGL on the CPU: SwiftShader through ANGLE, allowed explicitly.
                     "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver_path = next(shutil.which(name) for name in CHROMEDRIVER_CANDIDATES if shutil.which(name))
    driver = webdriver.Chrome(options=options, service=Service(driver_path))
    try:
        driver.get(Path(page).resolve().as_uri())
        count_script = ("return Array.from(document.querySelectorAll('canvas')).filter("
                        "c => c.getContext('webgl') || c.getContext('webgl2')).length")
        try:
            WebDriverWait(driver, timeout_s).until(lambda browser: browser.execute_script(count_script) > 0)
        except TimeoutException as error:
            logged = [entry.get("message", "") for entry in driver.get_log("browser")]
            raise RuntimeError(f"{page}: no WebGL canvas after {timeout_s:.0f} s; console: {logged}") from error
        time.sleep(settle_s)
        canvases = int(driver.execute_script(count_script))
        driver.save_screenshot(str(screenshot))
        log = driver.get_log("browser")
    finally:
        driver.quit()
    return PageRender(
        screenshot=Path(screenshot),
        webgl_canvases=canvases,
        errors=[entry.get("message", "") for entry in log if entry.get("level") == "SEVERE"],
        messages=[f"{entry.get('level')}: {entry.get('message', '')}" for entry in log],
        seconds=time.perf_counter() - start,
    )

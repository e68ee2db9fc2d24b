"""The documentation site as a reader meets it: built with ``mkdocs build --strict``, served
over HTTP on loopback and opened in headless Chromium. The home page, the CLI reference and
the API reference must render with their images, load nothing that fails and nothing from
outside the site; a screenshot of each goes to ``.ci/artifacts/`` (CI keeps them).

The site comes from ``$SNAIL_DOCS_SITE`` when .ci/run has built it, else it is built here.
Skipped, with the reason, where the docs extra (``pip install -e '.[docs]'``) or Debian's
``chromium`` and ``chromium-driver`` are missing.
"""

from __future__ import annotations

import contextlib
import functools
import http.server
import json
import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ROOT / ".ci" / "artifacts"
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run", "--window-size=1280,1400")
BROWSER_OWN = ("chrome://", "chrome-untrusted://", "chrome-extension://", "devtools://")
# page, what must be on it (a heading's text), how many images at least
PAGES = [
    ("index.html", "private camera localization in garbled circuits", 1),
    ("reference/cli.html", "snail-client localize", 0),
    ("reference/api.html", "localize_image", 0),
]


def _browser() -> tuple[str, str]:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("no headless browser: install Debian's chromium and chromium-driver "
                    "(.ci/run does, as root)")
    return chromium, driver


def _site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    given = os.environ.get("SNAIL_DOCS_SITE")
    if given:
        site = Path(given)
        assert (site / "index.html").is_file(), f"SNAIL_DOCS_SITE={given} holds no site"
        return site
    pytest.importorskip("mkdocs", reason="the docs extra is not installed "
                                         "(pip install -e '.[docs]')")
    site = tmp_path_factory.mktemp("site")
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                            str(site)], cwd=ROOT, capture_output=True, text=True, timeout=300,
                           env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert build.returncode == 0, f"mkdocs build --strict failed:\n{build.stderr}"
    return site


@contextlib.contextmanager
def _served(site: Path) -> Iterator[str]:
    """The site over HTTP on a free loopback port (a browser refuses some of a file:// site:
    the search worker)."""
    handler = functools.partial(_QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:  # the site loads quietly
        pass


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory):
    chromium, driver_path = _browser()
    webdriver = pytest.importorskip("selenium.webdriver",
                                    reason="selenium is not installed (the docs extra)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=options)
    try:
        driver.get("about:blank")  # leave the start page before any request is counted
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with _served(_site(tmp_path_factory)) as url:
        yield url


def _network(driver) -> tuple[list[str], list[str]]:
    """(every URL requested, every failure) since the last call, from Chrome's DevTools
    events: a request that failed to load, or answered 4xx/5xx. The browser's own pages
    (chrome://, its new-tab page loading as it starts) are not the site's and are left out."""
    urls: dict[str, str] = {}
    failures = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        method, params = message.get("method"), message.get("params", {})
        if method == "Network.requestWillBeSent":
            urls[params["requestId"]] = params["request"]["url"]
        url = urls.get(params.get("requestId"), "")
        if url.startswith(BROWSER_OWN):
            continue
        if method == "Network.loadingFailed" and not params.get("canceled"):
            failures.append(f"{params.get('errorText')} ({params.get('type')}) {url}")
        elif method == "Network.responseReceived" and params["response"]["status"] >= 400:
            failures.append(f"{params['response']['status']} {params['response']['url']}")
    return [u for u in urls.values() if not u.startswith(BROWSER_OWN)], failures


@pytest.mark.parametrize(("page", "text", "min_images"), PAGES)
def test_page_renders_with_its_images_and_no_failed_request(browser, base_url, page, text,
                                                             min_images):
    _network(browser)  # forget what came before
    browser.get(base_url + page)
    browser.execute_script("return document.fonts.ready")
    state = browser.execute_script(
        "return {title: document.title, text: document.body.innerText,"
        " images: Array.from(document.images).map(i => ({src: i.src, complete: i.complete,"
        " width: i.naturalWidth}))}")
    urls, failures = _network(browser)
    errors = [e["message"] for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    browser.save_screenshot(str(ARTIFACTS / f"docs-{page.replace('/', '-')[:-5]}.png"))

    assert text in state["text"], f"{page}: {text!r} is not on the page"
    assert len(state["images"]) >= min_images, state["images"]
    broken = [i["src"] for i in state["images"] if not (i["complete"] and i["width"] > 0)]
    assert not broken, f"{page}: images that did not render: {broken}"
    assert not failures, f"{page}: failed requests: {failures}"
    outside = [u for u in urls if not u.startswith((base_url, "data:", "blob:"))]
    assert not outside, f"{page}: requests outside the site: {outside}"
    assert not errors, f"{page}: console errors: {errors}"

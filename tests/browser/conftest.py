"""Browser fixtures: Debian's Chromium driven by Playwright against the session's real farm.

Every page a test opens is watched: a console error, an uncaught exception, a failed request or
an HTTP error status fails the test, unless the test declared that response as expected (a
validation error it provokes). The one tolerated failure is the dashboard closing its own
Server-Sent Events stream (net::ERR_ABORTED on /watch) when the user leaves a job page.
Screenshots go to tests/browser/artifacts/.
"""

from __future__ import annotations

import contextlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, sync_playwright

from renderfarm.client import pack_gltf

from ..conftest import CORNELL, ROOT

CHROMIUM = os.environ.get("RENDERFARM_CHROMIUM", "/usr/bin/chromium")
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
WEB_DIST = ROOT / "web" / "dist" / "index.html"

LAPTOP = {"width": 1366, "height": 800}
LARGE = {"width": 1920, "height": 1080}


@dataclass
class PageProblems:
    """What went wrong on a page; `expect` allows one HTTP error response the test provokes."""

    problems: list[str] = field(default_factory=list)
    expected: list[tuple[str, str, int]] = field(default_factory=list)
    seen_expected: list[str] = field(default_factory=list)

    def expect(self, method: str, path_pattern: str, status: int) -> None:
        self.expected.append((method, path_pattern, status))

    def _is_expected(self, method: str, url: str, status: int) -> bool:
        return any(m == method and re.search(p, url) and s == status for m, p, s in self.expected)

    def on_console(self, msg) -> None:
        if msg.type != "error":
            return
        # Chromium reports every HTTP error response on the console too; those the test
        # expects are checked as responses below, so their console echo is not a problem.
        if "Failed to load resource" in msg.text and self.seen_expected:
            status = re.search(r"status of (\d+)", msg.text)
            if status and any(s == int(status.group(1)) for _, _, s in self.expected):
                return
        self.problems.append(f"console error: {msg.text} at {msg.location}")

    def on_response(self, response) -> None:
        if response.status < 400:
            return
        method = response.request.method
        if self._is_expected(method, response.url, response.status):
            self.seen_expected.append(f"{method} {response.url} {response.status}")
            return
        self.problems.append(f"HTTP {response.status}: {method} {response.url}")

    def on_request_failed(self, request) -> None:
        failure = request.failure or ""
        if request.url.endswith("/watch") and "ERR_ABORTED" in failure:
            return  # the page closed its live stream (left the job page)
        self.problems.append(f"request failed: {request.method} {request.url}: {failure}")


@pytest.fixture(scope="module")
def browser() -> Browser:
    """Chromium for one test module. Module scope: Playwright's sync API runs an event loop in
    this thread while it is open, which would break asyncio.run() in tests collected later."""
    if not Path(CHROMIUM).exists():
        pytest.fail(
            f"{CHROMIUM} not found: `apt-get install chromium` (scripts/install-deps.sh does)"
        )
    if not WEB_DIST.exists():
        pytest.fail("web/dist is not built: run `make web`")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield b
        b.close()


@pytest.fixture()
def problems() -> PageProblems:
    return PageProblems()


@contextlib.contextmanager
def watched_page(browser: Browser, url: str, problems: PageProblems, **context_options):
    """A fresh page (laptop width) on the dashboard at `url`; fails on any problem it saw."""
    context = browser.new_context(viewport=LAPTOP, base_url=url, **context_options)
    pg = context.new_page()
    pg.set_default_timeout(30_000)
    pg.on("console", problems.on_console)
    pg.on("pageerror", lambda e: problems.problems.append(f"uncaught exception: {e}"))
    pg.on("response", problems.on_response)
    pg.on("requestfailed", problems.on_request_failed)
    yield pg
    found = list(problems.problems)
    context.close()
    assert not found, "problems on the page:\n" + "\n".join(found)


@pytest.fixture()
def page(browser: Browser, farm, problems: PageProblems) -> Page:
    """A fresh page on the shared farm's dashboard; fails the test on any problem."""
    with watched_page(browser, farm.url, problems, accept_downloads=True) as pg:
        yield pg


@pytest.fixture(scope="session")
def scene_glb(tmp_path_factory) -> Path:
    """The Cornell box packed into one .glb, as a user would upload it."""
    path = tmp_path_factory.mktemp("scenes") / "cornell-box.glb"
    path.write_bytes(pack_gltf(CORNELL))
    return path


def screenshot(pg: Page, name: str, full_page: bool = True) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    pg.evaluate("() => window.scrollTo(0, 0)")  # else the sticky top bar lands mid-page
    pg.screenshot(path=str(path), full_page=full_page)
    return path


def canvas_pixels(pg: Page) -> list[int]:
    """RGB bytes of the preview canvas as shown (after exposure or false colour)."""
    return pg.evaluate(
        """() => {
          const c = document.querySelector('canvas.preview');
          const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
          const out = [];
          for (let i = 0; i < d.length; i += 4) out.push(d[i], d[i + 1], d[i + 2]);
          return out;
        }"""
    )


def mean_abs_diff(a: list[int], b: list[int]) -> float:
    assert len(a) == len(b) and a, "images of different sizes"
    return sum(abs(x - y) for x, y in zip(a, b, strict=True)) / len(a)

"""Signing the dashboard in on a farm with API tokens: the session cookie carries the token
to every request, including the Server-Sent Events stream and the preview images."""

from __future__ import annotations

import pytest
from playwright.sync_api import Browser, Page, expect

from renderfarm.cli.localfarm import LocalFarm
from renderfarm.client import Client

from .conftest import PageProblems, canvas_pixels, mean_abs_diff, screenshot, watched_page
from .test_dashboard import wait_layer

TOKEN = "rf_browser-session-admin-secret"
# Long enough to still be rendering while the page watches it; cancelled at the end.
RENDER = {"width": 128, "height": 128, "tile_size": 32, "noise_threshold": 0, "max_spp": 65536}
DIALOG = ".session-dialog"


@pytest.fixture(scope="module")
def secured_farm(tmp_path_factory, worker_binary):
    """A farm whose server has an admin token (so every API request needs one), 2 workers."""
    data = tmp_path_factory.mktemp("secured-browser")
    env = {"RENDERFARM_ADMIN_TOKEN": TOKEN}
    with LocalFarm(workers=2, data_dir=data, threads=1, env=env) as running:
        yield running


@pytest.fixture()
def secured_page(browser: Browser, secured_farm, problems: PageProblems) -> Page:
    with watched_page(browser, secured_farm.url, problems) as pg:
        yield pg


def test_sign_in_watch_a_job_through_the_cookie_and_sign_out(
    secured_page: Page, secured_farm, problems: PageProblems, scene_glb
):
    page = secured_page
    # The only HTTP errors allowed: the job requests refused before signing in and after
    # signing out (the running job's preview image too, when a merge's event had the view
    # fetch it as the session ended), and the wrong token's sign-in. None before signing out:
    # checked below.
    problems.expect(
        "GET", r"/api/v1/jobs(/[0-9a-f-]+(/events|/convergence|/image\.png)?)?(\?.*)?$", 401
    )
    problems.expect("POST", r"/api/v1/session$", 401)

    page.goto("/#/jobs")
    dialog = page.locator(DIALOG)
    expect(dialog).to_be_visible()
    expect(dialog.get_by_role("heading")).to_have_text("Sign in")
    token_input = page.get_by_label("API token")
    expect(token_input).to_have_attribute("type", "password")
    expect(token_input).to_be_focused()
    expect(page.locator("#sign-out")).to_have_count(0)
    screenshot(page, "session-sign-in", full_page=False)

    # A wrong token, submitted from the keyboard: the server's message, no cookie.
    token_input.fill("rf_wrong-token")
    with page.expect_response(lambda r: r.url.endswith("/api/v1/session")) as refused:
        token_input.press("Enter")
    assert refused.value.status == 401
    expect(page.locator("#session-error")).to_contain_text("unknown API token")
    expect(dialog).to_be_visible()
    assert not page.context.cookies()

    # The right token: the dialog closes, the jobs list loads, Sign out appears.
    token_input.fill(TOKEN)
    page.get_by_role("button", name="Sign in").click()
    expect(dialog).to_be_hidden()
    expect(page.locator("#sign-out")).to_be_visible()
    expect(page.locator("h1")).to_have_text("Jobs")
    (cookie,) = page.context.cookies()
    assert cookie["name"] == "renderfarm_token" and cookie["value"] == TOKEN
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and cookie["path"] == "/"
    refused_before = len(problems.seen_expected)

    with Client(secured_farm.url, token=TOKEN, timeout=30) as client:
        job_id = client.submit(scene_glb, settings=RENDER, name="session-watch")["id"]
        try:
            page.goto(f"/#/jobs/{job_id}")
            expect(page.locator("h1")).to_have_text("session-watch")
            # Preview images fetched as the SSE stream reports merged samples: it changes.
            first_key = wait_layer(page, "rgb")
            first = canvas_pixels(page)
            wait_layer(page, "rgb", not_key=first_key)
            second = canvas_pixels(page)
            assert mean_abs_diff(first, second) > 0.5, "the preview did not change"
            screenshot(page, "session-job-running")
            assert len(problems.seen_expected) == refused_before, problems.seen_expected

            # Sign out: the cookie goes and the view asks for a token again.
            with page.expect_response(lambda r: r.url.endswith("/api/v1/session")) as out:
                page.locator("#sign-out").click()
            assert out.value.status == 204
            expect(dialog).to_be_visible()
            expect(page.get_by_label("API token")).to_be_focused()
            expect(page.locator("#sign-out")).to_have_count(0)
            assert not page.context.cookies()
        finally:
            client.cancel(job_id)

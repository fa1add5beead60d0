"""The dashboard in headless Chromium against a real local farm (2 workers): what users do."""

from __future__ import annotations

from playwright.sync_api import Page, expect

from ..waiting import wait_until
from .conftest import LARGE, canvas_pixels, mean_abs_diff, screenshot

# Small renders that take a few seconds on two one-thread workers, so progress can be watched.
WATCHED = {"width": 128, "height": 128, "tile_size": 32, "noise_threshold": 0, "max_spp": 256}
LONG = {"width": 128, "height": 128, "tile_size": 32, "noise_threshold": 0, "max_spp": 65536}


PROGRESS = '[data-stat="progress"] [role="progressbar"]'
LOADED = "() => document.querySelector('.viewer')?.dataset.loaded || ''"


def progress_now(page: Page, attribute: str = "aria-valuenow") -> int:
    return int(page.locator(PROGRESS).get_attribute(attribute))


def wait_layer(page: Page, layer: str, not_key: str = "") -> str:
    """Waits until the viewer shows `layer` (at another version than `not_key`); its key."""
    page.wait_for_function(
        f"([layer, old]) => {{ const k = ({LOADED})(); "
        "return k.startsWith(layer + ':') && k !== old; }",
        arg=[layer, not_key],
    )
    return page.locator(".viewer").get_attribute("data-loaded")


def wait_finished(client, job_id: str, timeout_s: float = 120) -> dict:
    def finished() -> dict | None:
        job = client.get(job_id)
        return job if job["state"] in ("completed", "failed", "cancelled") else None

    return wait_until(finished, timeout_s, f"job {job_id} to finish", poll_s=0.25)


def test_submit_through_the_form_and_watch_the_image_converge(page: Page, scene_glb, client):
    page.goto("/#/submit")
    expect(page.locator('[data-setting="max_spp"] input')).to_be_visible()
    screenshot(page, "submit-empty")
    page.locator("#scene-file").set_input_files(str(scene_glb))
    expect(page.locator(".file-info")).to_contain_text("cornell-box.glb")
    page.fill("#job-name", "browser-watch")
    for name, value in WATCHED.items():
        page.fill(f"#setting-{name}", str(value))
    is_submit = lambda r: r.url.endswith("/api/v1/jobs") and r.request.method == "POST"  # noqa: E731
    with page.expect_response(is_submit) as posted:
        page.click("button[type=submit]")
    assert posted.value.status == 201
    job_id = posted.value.json()["id"]
    page.wait_for_url(f"**/#/jobs/{job_id}")
    expect(page.locator("h1")).to_have_text("browser-watch")
    assert client.get(job_id)["settings"]["max_spp"] == WATCHED["max_spp"]

    # The preview changes between two moments, fetched as the stream reports merged samples.
    first_key = wait_layer(page, "rgb")
    first = canvas_pixels(page)
    wait_layer(page, "rgb", not_key=first_key)
    second = canvas_pixels(page)
    assert mean_abs_diff(first, second) > 0.5, "the preview did not change as samples were merged"
    screenshot(page, "job-running")

    # The progress bar advances: a value between 0 and all tiles, then all of them.
    total = progress_now(page, "aria-valuemax")
    assert total == 16
    page.wait_for_function(
        f"() => Number(document.querySelector('{PROGRESS}')?.getAttribute('aria-valuenow')) > 0",
        timeout=60_000,
    )
    seen = {progress_now(page)}

    # Switch to the relative-error heat map: a false-colour image unlike the render.
    rgb = canvas_pixels(page)
    page.get_by_role("radio", name="Relative error").check()
    wait_layer(page, "error")
    heat = canvas_pixels(page)
    assert mean_abs_diff(rgb, heat) > 5
    coloured = sum(1 for i in range(0, len(heat), 3) if abs(heat[i] - heat[i + 2]) > 8)
    assert coloured > len(heat) // 3 // 2, "the error layer is not colour-mapped"
    expect(page.locator(".legend-bar")).to_be_visible()
    page.get_by_role("checkbox", name="Tile grid").check()
    screenshot(page, "job-error-heatmap")

    expect(page.locator(".badge").first).to_have_text("completed", timeout=300_000)
    seen.add(progress_now(page))
    assert max(seen) == total and len(seen) >= 2, f"progress values seen: {sorted(seen)}"
    # Converged tiles are marked on the grid, one stop record per tile, the log tells the story.
    expect(page.locator(".tile-overlay rect.converged")).to_have_count(total)
    expect(page.locator(".job-lower table tbody tr")).to_have_count(total)
    expect(page.locator(".event-log")).to_contain_text("job finished")
    expect(page.locator(".plot-box path.series")).to_have_count(1)
    expect(page.locator(".plot-box .ref-line").first).to_be_visible()
    page.get_by_role("radio", name="Image").check()
    wait_layer(page, "rgb")
    # Exposure is applied on the canvas: +1 EV brightens the image.
    before = canvas_pixels(page)
    page.locator("#exposure").fill("1")
    brighter = canvas_pixels(page)
    assert sum(brighter) > sum(before) * 1.2
    page.locator("#exposure").fill("0")
    screenshot(page, "job-completed")
    page.set_viewport_size(LARGE)
    screenshot(page, "job-completed-large")

    # Downloads are the server's images.
    with page.expect_download() as png:
        page.get_by_role("link", name="Download PNG").click()
    assert png.value.suggested_filename == "browser-watch.png"
    with page.expect_download() as exr:
        page.get_by_role("link", name="Download EXR").click()
    assert exr.value.suggested_filename == "browser-watch.exr"


def test_the_server_validation_message_is_shown_beside_its_field(page: Page, problems, scene_glb):
    page.goto("/#/submit")
    page.click("button[type=submit]")  # no scene yet: said beside the drop zone, nothing sent
    expect(page.locator("#scene-error")).to_contain_text("Choose a scene file")

    page.locator("#scene-file").set_input_files(str(scene_glb))
    page.fill("#setting-max_spp", "0")
    problems.expect("POST", r"/api/v1/jobs$", 400)
    with page.expect_response(lambda r: r.url.endswith("/api/v1/jobs")) as posted:
        page.click("button[type=submit]")
    body = posted.value.json()
    assert posted.value.status == 400 and body["field"] == "settings.max_spp"
    message = page.locator('[data-setting="max_spp"] .field-error')
    expect(message).to_have_text(body["detail"])
    expect(page.locator("#setting-max_spp")).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#setting-max_spp")).to_be_focused()
    expect(page.locator('[data-setting="min_spp"] .field-error')).to_be_hidden()
    screenshot(page, "submit-validation-error")
    # Editing the field clears its message.
    page.fill("#setting-max_spp", "64")
    expect(message).to_be_hidden()


def test_cancel_a_job_and_see_its_state_change(page: Page, client, scene_glb):
    job = client.submit(scene_glb, name="browser-cancel", settings=LONG)
    page.goto(f"/#/jobs/{job['id']}")
    expect(page.locator(".badge").first).to_have_text("running", timeout=30_000)
    wait_layer(page, "rgb")
    page.get_by_role("button", name="Cancel job").click()
    expect(page.get_by_role("button", name="Keep rendering")).to_be_focused()
    page.get_by_role("button", name="Yes, cancel").click()
    expect(page.locator(".badge").first).to_have_text("cancelled")
    expect(page.get_by_role("button", name="Cancel job")).to_be_hidden()
    assert client.get(job["id"])["state"] == "cancelled"
    expect(page.locator(".event-log")).to_contain_text("job finished")
    screenshot(page, "job-cancelled")

    # The jobs list, filtered to cancelled jobs, shows it too.
    page.get_by_role("link", name="Jobs", exact=True).first.click()
    page.locator('[data-filter="cancelled"]').click()
    page.wait_for_url("**/#/jobs?state=cancelled")
    row = page.locator(f'tr[data-job-id="{job["id"]}"]')
    expect(row.locator(".badge")).to_have_text("cancelled")
    # The row was there before the filter too: wait until the other states' rows are gone
    # (a retrying assertion; a snapshot of the rows could be taken before the table redraws).
    others = page.locator('.jobs-table tbody .badge:not([data-state="cancelled"])')
    expect(others).to_have_count(0)
    screenshot(page, "jobs-cancelled-filter")


def test_jobs_list_updates_live_and_filters_by_state(page: Page, client, scene_glb):
    page.goto("/#/jobs")
    expect(page.locator("h1")).to_have_text("Jobs")
    # Long enough (several seconds on two worker threads) for the list's refresh to catch it
    # running; WATCHED's 256 spp can finish between two refreshes on a fast machine.
    settings = {**WATCHED, "max_spp": 2048, "priority": 3}
    job = client.submit(scene_glb, name="browser-list", settings=settings)
    row = page.locator(f'tr[data-job-id="{job["id"]}"]')
    expect(row).to_be_visible(timeout=10_000)  # appears without a reload
    expect(row.locator("td").nth(1)).to_have_text("-")  # owner: not served yet
    expect(row.locator("td").nth(8)).to_have_text("3")  # priority
    expect(row.locator(".badge")).to_have_text("running", timeout=30_000)
    screenshot(page, "jobs-running")
    # 2048 spp on two 1-thread workers: seconds on an idle machine, minutes on a busy one.
    expect(row.locator(".badge")).to_have_text("completed", timeout=300_000)
    expect(row.locator('[role="progressbar"]')).to_have_attribute("aria-valuenow", "16")
    page.set_viewport_size(LARGE)
    screenshot(page, "jobs-large")

    page.locator('[data-filter="completed"]').click()
    page.wait_for_url("**/#/jobs?state=completed")
    expect(row).to_be_visible()
    others = page.locator('.jobs-table tbody .badge:not([data-state="completed"])')
    expect(others).to_have_count(0)
    page.locator('[data-filter="queued"]').click()
    expect(page.locator(".empty")).to_have_text("No queued jobs.")


def test_workers_page_shows_both_workers_and_farm_throughput(page: Page, client, scene_glb):
    def both_workers() -> list[dict] | None:  # they connect a moment after the farm is up
        workers = client.workers()
        return workers if len(workers) >= 2 else None

    workers = wait_until(both_workers, 30, "2 workers connected", poll_s=0.2)
    ids = sorted(w["id"] for w in workers)
    assert len(ids) == 2
    job = client.submit(scene_glb, name="browser-workers", settings=LONG)
    try:
        page.goto("/#/workers")
        for worker_id in ids:
            expect(page.locator(f'tr[data-worker-id="{worker_id}"]')).to_be_visible()
        expect(page.locator('[data-stat="workers"] .stat-value')).to_have_text("2")
        # Throughput sampled every 2 s: wait for a line on the chart.
        samples_chart = page.locator(".chart-row .card").first
        expect(samples_chart.locator("path.series")).to_have_count(1, timeout=15_000)
        busy = page.locator(".workers-table .badge").first
        expect(busy).to_have_text("rendering", timeout=15_000)
        screenshot(page, "workers")
        page.set_viewport_size(LARGE)
        screenshot(page, "workers-large")
    finally:
        client.cancel(job["id"])
        wait_finished(client, job["id"])


def test_keyboard_only_navigation(page: Page, client, scene_glb):
    job = client.submit(scene_glb, name="browser-keys", settings=WATCHED)
    page.goto("/#/jobs")
    expect(page.locator(f'tr[data-job-id="{job["id"]}"]')).to_be_visible()
    # Skip link, then the brand and the main navigation, by Tab alone.
    page.keyboard.press("Tab")
    expect(page.locator(".skip-link")).to_be_focused()
    page.keyboard.press("Tab")
    page.keyboard.press("Tab")
    page.keyboard.press("Tab")
    expect(page.locator('[data-nav="workers"]')).to_be_focused()
    page.keyboard.press("Enter")
    expect(page.locator("h1")).to_have_text("Workers")
    page.goto(f"/#/jobs/{job['id']}")
    image = page.get_by_role("radio", name="Image")
    image.focus()
    page.keyboard.press("ArrowRight")  # radio group: the next layer
    expect(page.get_by_role("radio", name="Relative error")).to_be_checked()
    wait_layer(page, "error")
    page.keyboard.press("Tab")  # the exposure slider is hidden for the heat map: next is Tile grid
    expect(page.get_by_role("checkbox", name="Tile grid")).to_be_focused()
    page.keyboard.press("Space")
    expect(page.get_by_role("checkbox", name="Tile grid")).to_be_checked()
    wait_finished(client, job["id"])


def test_a_narrow_window_keeps_every_page_usable(page: Page, client):
    page.set_viewport_size({"width": 420, "height": 900})
    job_id = client.list()["jobs"][0]["id"]
    for name, url in [("jobs", "/#/jobs"), ("job", f"/#/jobs/{job_id}"), ("submit", "/#/submit")]:
        page.goto(url)
        page.wait_for_load_state("networkidle") if name != "job" else page.wait_for_timeout(1000)
        width = page.evaluate("() => document.documentElement.scrollWidth")
        assert width <= 420, f"{name} page overflows horizontally ({width} px)"
        screenshot(page, f"narrow-{name}")


def test_job_control_pause_resume_edit_and_continue(page: Page, problems, client, scene_glb):
    job = client.submit(scene_glb, name="browser-control", settings=LONG)
    page.goto(f"/#/jobs/{job['id']}")
    expect(page.locator(".badge").first).to_have_text("running", timeout=30_000)
    expect(page.get_by_role("button", name="Resume")).to_be_hidden()
    page.get_by_role("button", name="Pause").click()
    expect(page.locator(".badge").first).to_have_text("paused")
    expect(page.get_by_role("button", name="Pause")).to_be_hidden()
    assert client.get(job["id"])["state"] == "paused"
    screenshot(page, "job-paused")
    page.get_by_role("button", name="Resume").click()
    expect(page.locator(".badge").first).to_have_text("running")
    page.fill("#edit-priority", "7")
    page.fill("#edit-name", "browser-renamed")
    page.get_by_role("button", name="Save").click()
    expect(page.locator("h1")).to_have_text("browser-renamed")
    got = client.get(job["id"])
    assert (got["settings"]["priority"], got["name"]) == (7, "browser-renamed")
    page.get_by_role("button", name="Cancel job").click()
    page.get_by_role("button", name="Yes, cancel").click()
    expect(page.locator(".badge").first).to_have_text("cancelled")

    # A completed job is carried on to more samples; a refusal names its field.
    small = {"width": 64, "height": 64, "tile_size": 32, "noise_threshold": 0, "max_spp": 16}
    done = client.submit(scene_glb, name="browser-continue", settings=small)
    assert wait_finished(client, done["id"])["state"] == "completed"
    page.goto(f"/#/jobs/{done['id']}")
    expect(page.locator(".badge").first).to_have_text("completed")
    expect(page.locator("#continue-max-spp")).to_have_value("32")
    problems.expect("POST", r"/continue$", 400)
    page.fill("#continue-noise-threshold", "0.5")
    page.get_by_role("button", name="Continue").click()
    message = page.locator(".control-message")
    expect(message).to_contain_text("settings.noise_threshold")
    expect(message).to_have_attribute("data-field", "settings.noise_threshold")
    page.fill("#continue-noise-threshold", "0")
    page.get_by_role("button", name="Continue").click()
    expect(page.locator('[data-stat="spp"]')).to_contain_text("/ 32", timeout=30_000)
    expect(page.locator(".badge").first).to_have_text("completed", timeout=60_000)
    assert client.get(done["id"])["progress"]["mean_spp"] == 32
    expect(page.locator('.settings-list [data-setting="max_spp"]')).to_have_text("32")
    expect(page.locator(".event-log")).to_contain_text("job continued")
    screenshot(page, "job-continued")


def test_workers_page_drains_and_enables_a_worker(page: Page, client):
    ids = sorted(w["id"] for w in client.workers())
    assert ids, "the session farm has workers"
    page.goto("/#/workers")
    row = page.locator(f'tr[data-worker-id="{ids[0]}"]')
    expect(row.locator('[data-field="mode"]')).to_have_text("active")
    try:
        row.locator('button[data-action="drain"]').click()
        # Idle, so nothing to finish: drained at once.
        expect(row.locator('[data-field="mode"]')).to_have_text("drained")
        assert {w["id"]: w["state"] for w in client.workers()}[ids[0]] == "drained"
        row.locator('button[data-action="enable"]').click()
        expect(row.locator('[data-field="mode"]')).to_have_text("active")
        assert {w["id"]: w["state"] for w in client.workers()}[ids[0]] == "active"
    finally:
        client.enable_worker(ids[0])

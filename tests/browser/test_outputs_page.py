"""The job page's outputs in headless Chromium: the denoised layer, the numbers of the heat
maps' colour bars, and the notice of a job that completed short of its noise target."""

from __future__ import annotations

import json

import numpy as np
from playwright.sync_api import Page, expect

from renderfarm.infra.images import read_exr

from ..conftest import CORNELL
from ..test_cryptomatte_farm import SETTINGS as CRYPTO_SETTINGS
from ..test_cryptomatte_farm import H, W, scene
from ..waiting import wait_until
from .conftest import canvas_pixels, mean_abs_diff, screenshot

# 8 spp cannot reach 0.1% on the Cornell box: every tile stops at max_spp.
SHORT = {"width": 64, "height": 64, "tile_size": 32, "noise_threshold": 0.001, "min_spp": 4,
         "max_spp": 8, "denoise": True}  # fmt: skip


def wait_layer(page: Page, layer: str) -> None:
    page.wait_for_function(
        "(layer) => (document.querySelector('.viewer')?.dataset.loaded || '')"
        ".startsWith(layer + ':')",
        arg=layer,
    )


def percent(fraction: float) -> str:
    """As the dashboard writes a fraction: 2 decimals under 10%, else 1."""
    p = 100 * fraction
    return f"{p:.2f}%" if p < 10 else f"{p:.1f}%"


def test_denoised_layer_scales_and_shortfall(page: Page, client, tmp_path):
    job = client.submit(CORNELL, settings=SHORT, name="short of target")
    job = wait_until(
        lambda: (j := client.get(job["id"]))["state"] in ("completed", "failed") and j,
        300, "the job to finish",
    )  # fmt: skip
    assert job["state"] == "completed", job["error"]
    exr = tmp_path / "job.exr"
    client.save_image(job["id"], exr, "exr")
    channels = read_exr(str(exr))

    page.goto(f"/#/jobs/{job['id']}")
    notice = page.locator('[data-field="shortfall"]')
    expect(notice).to_have_text(
        "Completed without reaching the noise target of 0.10%: 4 of 4 tiles stopped before it, "
        f"4 at max_spp (8 spp); image error {percent(job['progress']['error'])}."
    )
    wait_layer(page, "rgb")
    rgb = canvas_pixels(page)

    # The spp heat map: its bar runs from 0 to the 8 samples every pixel has.
    page.get_by_role("radio", name="Samples / pixel").check()
    wait_layer(page, "spp")
    expect(page.locator(".legend-bar .legend-min")).to_have_text("0")
    expect(page.locator(".legend-bar .legend-max")).to_have_text("8")

    # The error heat map: its top is the largest relative error of the image.
    page.get_by_role("radio", name="Relative error").check()
    wait_layer(page, "error")
    shown = float(page.locator(".legend-bar").get_attribute("data-max"))
    top = float(np.max(channels["error"][np.isfinite(channels["error"])]))
    assert abs(shown - top) <= 1e-6 * top, (shown, top)
    expect(page.locator(".legend-bar .legend-max")).to_have_text(percent(top))
    screenshot(page, "job-error-scale")

    # The denoised layer: smoother than the noisy image, with the exposure control.
    page.get_by_role("radio", name="Denoised").check()
    wait_layer(page, "denoised")
    denoised = canvas_pixels(page)
    assert mean_abs_diff(rgb, denoised) > 1
    expect(page.locator("#exposure")).to_be_visible()
    expect(page.get_by_role("link", name="Download denoised PNG")).to_be_visible()
    screenshot(page, "job-denoised")


def test_a_job_without_denoise_offers_no_denoised_layer(page: Page, client):
    job = client.submit(CORNELL, settings={**SHORT, "denoise": False, "noise_threshold": 0})
    wait_until(lambda: client.get(job["id"])["state"] == "completed", 300, "the job to complete")
    page.goto(f"/#/jobs/{job['id']}")
    wait_layer(page, "rgb")
    expect(page.get_by_role("radio", name="Image")).to_be_visible()
    expect(page.get_by_role("radio", name="Denoised")).to_have_count(0)
    expect(page.locator('[data-field="shortfall"]')).to_be_hidden()  # no target: no notice


def test_denoise_is_a_checkbox_of_the_submit_form(page: Page, scene_glb):
    page.goto("/#/submit")
    box = page.locator("#setting-denoise")
    expect(box).to_have_attribute("type", "checkbox")
    expect(box).not_to_be_checked()
    page.locator("#scene-file").set_input_files(str(scene_glb))
    for name, value in {"width": 32, "height": 32, "tile_size": 16, "max_spp": 4}.items():
        page.fill(f"#setting-{name}", str(value))
    box.check()
    is_submit = lambda r: r.url.endswith("/api/v1/jobs") and r.request.method == "POST"  # noqa: E731
    with page.expect_response(is_submit) as posted:
        page.click("button[type=submit]")
    assert posted.value.status == 201
    assert posted.value.json()["settings"]["denoise"] is True
    page.wait_for_url(f"**/#/jobs/{posted.value.json()['id']}")
    expect(page.get_by_role("radio", name="Denoised")).to_be_visible()


def test_the_viewer_names_the_object_under_the_pointer(page: Page, client, tmp_path):
    """With Cryptomatte on, moving the pointer over the image names the glTF node, material and
    root node under it (GET .../mattes), from the scene of tests/test_cryptomatte_farm.py: the
    wheel (material rubber, under the root car) at pixel (12, 24), the lamp at (8, 5)."""
    path = tmp_path / "car.gltf"
    path.write_text(json.dumps(scene()))
    job = client.submit(str(path), settings={**CRYPTO_SETTINGS, "max_spp": 4},
                        name="cryptomatte")  # fmt: skip
    job = wait_until(
        lambda: (j := client.get(job["id"]))["state"] in ("completed", "failed") and j,
        300, "the job to finish",
    )  # fmt: skip
    assert job["state"] == "completed", job["error"]
    page.goto(f"/#/jobs/{job['id']}")
    wait_layer(page, "rgb")
    expect(page.locator('.viewer input[value="crypto_object"]')).to_have_count(1)
    box = page.locator("canvas.preview").bounding_box()
    pointer = page.locator(".viewer-pointer")

    def hover(x: int, y: int) -> None:
        page.mouse.move(box["x"] + (x + 0.5) / W * box["width"],
                        box["y"] + (y + 0.5) / H * box["height"])  # fmt: skip

    hover(12, 24)
    expect(pointer).to_have_text("(12, 24) object wheel (100%) · material rubber (100%) · "
                                 "asset car (100%)")  # fmt: skip
    hover(8, 5)
    expect(pointer).to_have_text("(8, 5) object lamp (100%) · material paint (100%)")
    hover(40, 2)
    expect(pointer).to_have_text("(40, 2) nothing")
    screenshot(page, "cryptomatte-pointer")
    page.mouse.move(box["x"] - 20, box["y"] - 20)  # off the image: the line empties
    expect(pointer).to_have_text("")


def test_the_layer_switch_has_the_lobes_and_a_layer_per_light_group(page: Page, client):
    settings = {**SHORT, "denoise": False, "noise_threshold": 0, "aovs": ["lobes", "light_groups"]}
    job = client.submit(CORNELL, settings=settings, name="passes")
    wait_until(lambda: client.get(job["id"])["state"] == "completed", 300, "the job to complete")
    page.goto(f"/#/jobs/{job['id']}")
    wait_layer(page, "rgb")
    for name in ("Diffuse direct", "Diffuse indirect", "Emission", "Background"):
        expect(page.get_by_role("radio", name=name)).to_be_visible()
    # The Cornell box's groups: its emissive quad (node `light`) and the environment (black).
    page.get_by_role("radio", name="Light light").check()
    wait_layer(page, "light_group.light")
    lit = canvas_pixels(page)
    expect(page.locator("#exposure")).to_be_visible()  # a radiance: exposure applies
    page.get_by_role("radio", name="Light environment").check()
    wait_layer(page, "light_group.environment")
    dark = canvas_pixels(page)
    assert np.mean(lit) > 20 and max(dark) == 0

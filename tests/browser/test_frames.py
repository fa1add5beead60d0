"""An animation's job page in headless Chromium: the frame strip fills in live as frames finish,
a frame is chosen by click, key and slider (and kept in the URL), the image, heat maps, tile
grid and stop records follow the frame, and the preview movie plays; a still has no strip.

The scene is an emissive square that a LINEAR sampler moves along x, written here: where it
shows in each frame is worked out from the camera (see square_column)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from ..test_animation_pose import GltfBuilder
from ..waiting import wait_until
from .conftest import canvas_pixels, screenshot

SIZE = 32
YFOV = 0.8  # radians
CAMERA_Z = 3.0
HALF = 0.25  # half the square's side
FPS = 4
FRAMES = [1, 2, 3, 4]  # "1-4": glTF times 0.25, 0.5, 0.75 and 1 s
ANIMATED = {
    "width": SIZE,
    "height": SIZE,
    "tile_size": 16,  # 4 tiles a frame
    "frames": "1-4",
    "fps": FPS,
    "max_spp": 16,
    "noise_threshold": 0,
}
STILL = {"width": SIZE, "height": SIZE, "tile_size": 16, "max_spp": 16, "noise_threshold": 0}

STRIP = ".frame-strip"
CELLS = ".frame-strip .frame-cell"


def square_x(t: float) -> float:
    """The square's centre at glTF time t: LINEAR from x = -1 at t = 0 to x = 1 at t = 1."""
    return -1.0 + 2.0 * min(max(t, 0.0), 1.0)


def square_column(frame: int) -> float:
    """The image column (in pixels, 0 at the left edge) of the square's centre in a frame: a
    pinhole camera at z = CAMERA_Z looking down -z with vertical field of view YFOV, square
    pixels, so x at depth CAMERA_Z lands at SIZE/2 * (1 + x / (CAMERA_Z tan(YFOV/2)))."""
    x = square_x(frame / FPS)
    return SIZE / 2 * (1 + x / (CAMERA_Z * math.tan(YFOV / 2)))


def write_scene(path: Path) -> None:
    b = GltfBuilder()
    corners = [[-HALF, -HALF, 0], [HALF, -HALF, 0], [HALF, HALF, 0], [-HALF, HALF, 0]]
    positions = b.add(corners, 5126, "VEC3")
    indices = b.add([0, 1, 2, 0, 2, 3], 5123, "SCALAR")
    times = b.add([0.0, 1.0], 5126, "SCALAR")
    moves = b.add([[square_x(0.0), 0, 0], [square_x(1.0), 0, 0]], 5126, "VEC3")
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 0, CAMERA_Z]}],
        "cameras": [
            {
                "type": "perspective",
                "perspective": {"yfov": YFOV, "aspectRatio": 1.0, "znear": 0.01},
            }
        ],
        "materials": [
            {"emissiveFactor": [1, 1, 1], "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]}}
        ],
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": positions}, "indices": indices, "material": 0}
                ]
            }
        ],
        "animations": [
            {
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                "samplers": [{"input": times, "output": moves, "interpolation": "LINEAR"}],
            }
        ],
        **b.buffers(),
    }
    path.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def moving_square(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("frames") / "moving-square.gltf"
    write_scene(path)
    return path


def brightness_column(pixels: list[int]) -> float:
    """The brightness-weighted mean column of the canvas (RGB bytes, SIZE x SIZE)."""
    weight = total = 0.0
    for i in range(0, len(pixels), 3):
        v = pixels[i] + pixels[i + 1] + pixels[i + 2]
        weight += v
        total += v * ((i // 3) % SIZE + 0.5)
    assert weight > 0, "the canvas is black"
    return total / weight


def wait_viewer_frame(page: Page, frame: int, layer: str = "rgb", finished: bool = True) -> None:
    """Waits until the viewer shows `frame` of the animation in `layer`; `finished`: its final
    image (the frame done), not a version loaded while it was rendering, which the viewer may
    still show for a moment after the frame is done on a busy machine."""
    page.wait_for_function(
        """([frame, layer, finished]) => {
          const v = document.querySelector('.viewer');
          const src = document.querySelector('canvas.preview')?.dataset.src || '';
          const caption = document.querySelector('.viewer-caption')?.textContent || '';
          return v?.dataset.frame === String(frame)
            && (v?.dataset.loaded || '').startsWith(layer + ':')
            && src.includes(`/frames/${frame}/image.png?layer=${layer}&`)
            && (!finished || caption.endsWith(', finished'));
        }""",
        arg=[frame, layer, finished],
    )


def pressed_frame(page: Page) -> str | None:
    return page.locator(f'{CELLS}[aria-pressed="true"]').get_attribute("data-frame")


def test_the_frame_strip_follows_an_animation_frame_by_frame(
    page: Page, client, moving_square, problems
):
    # Both workers drained: the job stays queued until the page is watching it.
    def both_workers() -> list[dict] | None:  # they connect a moment after the farm is up
        workers = client.workers()
        return workers if len(workers) >= 2 else None

    ids = [w["id"] for w in wait_until(both_workers, 30, "2 workers connected", poll_s=0.2)]
    try:
        for worker_id in ids:
            client.drain_worker(worker_id)
        job = client.submit(moving_square, name="browser-frames", settings=ANIMATED)
        page.goto(f"/#/jobs/{job['id']}")
        cells = page.locator(CELLS)
        expect(cells).to_have_count(4)
        for cell, frame in zip(cells.all(), FRAMES, strict=True):
            expect(cell).to_have_attribute("data-frame", str(frame))
            expect(cell).to_have_attribute("data-state", "queued")
            expect(cell).to_have_attribute("aria-label", f"Frame {frame}: queued")
        expect(page.locator('[data-stat="frames"] .stat-value')).to_have_text("0 / 4")
        expect(page.locator('[data-field="movie"]')).to_be_hidden()  # no frame finished yet
        # The first frame is shown by default (its image is all black while queued).
        assert pressed_frame(page) == "1"
        wait_viewer_frame(page, 1, finished=False)
        screenshot(page, "frames-queued")
    finally:
        for worker_id in ids:
            client.enable_worker(worker_id)

    # The strip fills in live (no reload) as the frames finish.
    for frame in FRAMES:
        cell = page.locator(f'{CELLS}[data-frame="{frame}"]')
        expect(cell).to_have_attribute("data-state", "done", timeout=120_000)
        expect(cell).to_have_attribute("aria-label", re.compile(rf"^Frame {frame}: done, error "))
    expect(page.locator(".badge").first).to_have_text("completed", timeout=60_000)
    expect(page.locator('[data-stat="frames"] .stat-value')).to_have_text("4 / 4")
    expect(page.locator(".frame-summary")).to_have_text("4 of 4 frames done")
    server_frames = client.frames(job["id"])
    assert [f["state"] for f in server_frames] == ["done"] * 4

    # Frame 1's image: the square left of centre, where the camera puts it.
    wait_viewer_frame(page, 1)
    first = brightness_column(canvas_pixels(page))
    assert abs(first - square_column(1)) < 1.5, (first, square_column(1))

    # Clicking frame 3 shows frame 3, and the URL says so.
    page.locator(f'{CELLS}[data-frame="3"]').click()
    wait_viewer_frame(page, 3)
    assert pressed_frame(page) == "3"
    page.wait_for_url(re.compile(rf"#/jobs/{job['id']}\?frame=3$"))
    third = brightness_column(canvas_pixels(page))
    assert abs(third - square_column(3)) < 1.5, (third, square_column(3))
    expect(page.locator("#frame-slider")).to_have_value("2")
    expect(page.locator(".frame-output")).to_have_text("Frame 3 (3 of 4), done")
    # The downloads are frame 3's.
    png = page.get_by_role("link", name="Download PNG")
    expect(png).to_have_attribute("href", re.compile(r"/frames/3/image\.png\?layer=rgb$"))
    with page.expect_download() as download:
        png.click()
    assert download.value.suggested_filename == "browser-frames-frame3.png"

    # The tile grid and stop records are frame 3's: its 4 tiles, numbered 0..3 in its grid.
    page.get_by_role("checkbox", name="Tile grid").check()
    expect(page.locator(".tile-overlay rect")).to_have_count(4)
    expect(page.locator(".tile-overlay rect.converged")).to_have_count(4)
    expect(page.locator(".job-lower table tbody tr")).to_have_count(4)
    expect(page.locator(".job-lower table tbody tr td:first-child")).to_have_text(
        ["0", "1", "2", "3"]
    )
    expect(page.locator(".job-lower .card").first).to_contain_text(
        "4 of 4 tiles of frame 3 stopped"
    )
    expect(page.locator(".event-log")).to_contain_text("frame finished")

    # The spp heat map of frame 3: 16 samples everywhere.
    page.get_by_role("radio", name="Samples / pixel").check()
    wait_viewer_frame(page, 3, "spp")
    expect(page.locator(".legend-bar .legend-max")).to_have_text("16")
    screenshot(page, "frames-spp-frame3")
    page.get_by_role("radio", name="Image").check()
    wait_viewer_frame(page, 3)

    # Keys move along the strip: right to frame 4, Home to frame 1.
    page.locator(f'{CELLS}[data-frame="3"]').focus()
    page.keyboard.press("ArrowRight")
    expect(page.locator(f'{CELLS}[data-frame="4"]')).to_be_focused()
    wait_viewer_frame(page, 4)
    page.wait_for_url(re.compile(r"\?frame=4$"))
    fourth = brightness_column(canvas_pixels(page))
    assert abs(fourth - square_column(4)) < 1.5, (fourth, square_column(4))
    page.keyboard.press("Home")
    wait_viewer_frame(page, 1)
    assert pressed_frame(page) == "1"
    # The slider scrubs: its third step is frame 3 (from memory now: no new image request).
    page.locator("#frame-slider").fill("2")
    wait_viewer_frame(page, 3)
    assert pressed_frame(page) == "3"
    assert abs(brightness_column(canvas_pixels(page)) - third) < 1e-9
    page.wait_for_url(re.compile(r"\?frame=3$"))  # the address follows a moment later

    # Reloading keeps the frame the URL names; so does opening the link afresh.
    page.reload()
    expect(page.locator(CELLS)).to_have_count(4)
    wait_viewer_frame(page, 3)
    assert pressed_frame(page) == "3"
    page.goto(f"/#/jobs/{job['id']}?frame=2")
    wait_viewer_frame(page, 2)
    assert pressed_frame(page) == "2"
    # A frame the job does not render shows the first, and the URL drops it.
    page.goto(f"/#/jobs/{job['id']}?frame=9")
    wait_viewer_frame(page, 1)
    page.wait_for_url(re.compile(rf"#/jobs/{job['id']}$"))
    screenshot(page, "frames-done")
    # A narrow window: the strip wraps, nothing overflows sideways.
    page.set_viewport_size({"width": 420, "height": 900})
    expect(page.locator(f'{CELLS}[data-frame="4"]')).to_be_visible()
    width = page.evaluate("() => document.documentElement.scrollWidth")
    assert width <= 420, f"the animation's page overflows horizontally ({width} px)"
    screenshot(page, "narrow-frames")


def test_a_still_has_no_frame_strip(page: Page, client, moving_square):
    job = client.submit(moving_square, name="browser-still", settings=STILL)
    page.goto(f"/#/jobs/{job['id']}?frame=3")  # a frame in the URL means nothing to a still
    expect(page.locator(".badge").first).to_have_text("completed", timeout=120_000)
    page.wait_for_function(
        "() => (document.querySelector('canvas.preview')?.dataset.src || '')"
        ".includes('/image.png?layer=rgb&')"
    )
    expect(page.locator(STRIP)).to_have_count(0)
    expect(page.locator('[data-stat="frames"]')).to_have_count(0)
    expect(page.locator('[data-field="movie"]')).to_have_count(0)
    assert page.locator(".viewer").get_attribute("data-frame") is None
    assert "/frames/" not in page.locator("canvas.preview").get_attribute("data-src")
    expect(page.get_by_role("link", name="Download PNG")).to_have_text("Download PNG")
    expect(page.locator(".job-lower .card").first).to_contain_text("4 of 4 tiles stopped")


def test_the_preview_movie_plays_and_downloads(page: Page, client, moving_square):
    paths = client.http.get("/openapi.json").json()["paths"]
    if "/api/v1/jobs/{job_id}/movie.mp4" not in paths:
        pytest.fail("the server does not serve GET /api/v1/jobs/{job_id}/movie.mp4 yet")
    job = client.submit(moving_square, name="browser-movie", settings=ANIMATED)
    wait_until(
        lambda: client.get(job["id"])["state"] == "completed", 120, "the animation to finish"
    )
    page.goto(f"/#/jobs/{job['id']}")
    panel = page.locator('[data-field="movie"]')
    expect(panel).to_be_visible()
    expect(panel).to_contain_text("4 of 4 frames finished, 1.00 s at 4 fps")
    link = panel.get_by_role("link", name="Download MP4")
    expect(link).to_have_attribute("href", re.compile(rf"/api/v1/jobs/{job['id']}/movie\.mp4"))
    panel.get_by_role("button", name="Play preview movie").click()
    video = panel.locator("video")
    expect(video).to_be_visible()
    # Chromium read the movie's header: 4 frames at 4 fps last a second.
    expect(video).to_have_attribute("data-ready", "true", timeout=30_000)
    duration = video.evaluate("v => v.duration")
    assert abs(duration - len(FRAMES) / FPS) < 0.3, duration
    assert video.evaluate("v => [v.videoWidth, v.videoHeight]") == [SIZE, SIZE]
    screenshot(page, "frames-movie")
    with page.expect_download() as download:
        link.click()
    # The server's Content-Disposition names the file (it wins over the link's download name).
    assert download.value.suggested_filename == f"{job['id']}.mp4"
    head = Path(download.value.path()).read_bytes()[:12]
    assert head[4:8] == b"ftyp", head  # an MP4 (ISO base media file)

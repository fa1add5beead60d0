"""The task log: a worker's scene-loader warnings about a job's tasks reach the job's events
(task_warning, once per message and job, naming the worker, tile, batch and frame) and the
job page's Task log card; a job without any has no card.

The scene is test_frames.py's moving square with an extension the loader does not implement
listed in extensionsUsed (not required), which the loader warns about and ignores."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from ..waiting import wait_until
from .test_frames import ANIMATED, STILL, write_scene

UNKNOWN = "EXT_renderfarm_not_implemented"


@pytest.fixture(scope="module")
def warned_scene(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("tasklog") / "warned.gltf"
    write_scene(path)
    doc = json.loads(path.read_text())
    doc["extensionsUsed"] = [UNKNOWN]
    path.write_text(json.dumps(doc))
    return path


def test_loader_warnings_are_logged_once_per_job_and_shown(page: Page, client, warned_scene):
    # Both workers of the shared farm, which connect a moment after it is up.
    workers = wait_until(lambda: {w["id"] for w in client.workers()} if len(client.workers()) == 2
                         else None, 60, "two workers")  # fmt: skip
    job = client.submit(warned_scene, settings=ANIMATED, name="warned")
    job = client.wait(job["id"], poll_s=0.2, timeout_s=300)
    assert job["state"] == "completed", job["error"]
    warnings = [e for e in client.events(job["id"]) if e["kind"] == "task_warning"]
    # Every task of every frame rendered the scene; the message is in the log once.
    assert len(warnings) == 1, warnings
    data = warnings[0]["data"]
    assert UNKNOWN in data["message"] and "not supported" in data["message"]
    assert data["worker"] in workers
    assert data["frame"] in (1, 2, 3, 4) and 0 <= data["tile"] < 16 and data["batch"] >= 0

    page.goto(f"/#/jobs/{job['id']}")
    log = page.locator(".card", has=page.locator("h2", has_text="Task log"))
    expect(log).to_be_visible()
    rows = log.locator("tbody tr")
    expect(rows).to_have_count(1)
    expect(rows.first).to_contain_text(UNKNOWN)
    expect(rows.first).to_contain_text(data["worker"])
    local = data["tile"] - (data["frame"] - 1) * 4  # 4 tiles a frame
    place = f"frame {data['frame']}, tile {local}, batch {data['batch']}"
    expect(rows.first).to_contain_text(place)

    # Another job of the same scene logs it again (the log is the job's).
    again = client.wait(client.submit(warned_scene, settings=STILL)["id"], poll_s=0.2)
    kinds = [e["kind"] for e in client.events(again["id"])]
    assert kinds.count("task_warning") == 1


def test_a_job_without_warnings_has_no_task_log(page: Page, client, tmp_path):
    clean = tmp_path / "clean.gltf"
    write_scene(clean)
    job = client.wait(client.submit(clean, settings=STILL)["id"], poll_s=0.2, timeout_s=300)
    assert not [e for e in client.events(job["id"]) if e["kind"].startswith("task_")]
    page.goto(f"/#/jobs/{job['id']}")
    expect(page.locator(".badge").first).to_have_text("completed")
    expect(page.locator(".event-log li").first).to_be_visible()
    expect(page.locator(".card", has=page.locator("h2", has_text="Task log"))).to_be_hidden()

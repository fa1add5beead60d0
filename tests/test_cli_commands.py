"""The client commands of the CLI against a running farm, scripted through --json."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from .conftest import CORNELL

CLI = [sys.executable, "-m", "renderfarm"]
TINY = ["--width", "32", "--height", "32", "--tile-size", "16", "--spp", "4"]


def _run(farm, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    environment = {**os.environ, "RENDERFARM_URL": farm.url, **(env or {})}
    environment.pop("RENDERFARM_TOKEN", None)
    return subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=300,
                          env={**environment, **(env or {})})  # fmt: skip


def test_submit_watch_get_ls_rm_with_json(farm):
    submitted = _run(farm, "submit", str(CORNELL), "--json", "--name", "cli", *TINY)
    assert submitted.returncode == 0, submitted.stderr
    job = json.loads(submitted.stdout)
    watched = _run(farm, "watch", job["id"], "--json")
    assert watched.returncode == 0, watched.stderr
    updates = [json.loads(line) for line in watched.stdout.splitlines()]
    assert updates and updates[-1]["state"] == "completed"
    got = json.loads(_run(farm, "get", job["id"], "--json").stdout)
    assert got["progress"]["mean_spp"] == 4 and got["stops"]
    listed = json.loads(_run(farm, "ls", "--json", "--limit", "500").stdout)
    assert job["id"] in {j["id"] for j in listed["jobs"]}
    workers = json.loads(_run(farm, "workers", "--json").stdout)
    assert len(workers) == 2
    removed = _run(farm, "rm", job["id"])
    assert removed.returncode == 0 and f"{job['id']} deleted" in removed.stdout
    gone = _run(farm, "get", job["id"])
    assert gone.returncode == 1 and "no job" in gone.stderr


def test_watch_draws_a_progress_bar_and_cancel_works(farm):
    submitted = _run(farm, "submit", str(CORNELL), *TINY[:-2], "--spp", "100000",
                     "--noise-threshold", "0.0001")  # fmt: skip
    job_id = submitted.stdout.strip()
    cancelled = _run(farm, "cancel", job_id, "--json")
    assert json.loads(cancelled.stdout)["state"] == "cancelled"
    watched = _run(farm, "watch", job_id)
    assert watched.returncode == 1  # the job did not complete
    line = watched.stderr.strip().splitlines()[-1]
    assert "tiles" in line and "spp" in line and "ETA" in line and "cancelled" in line


def test_a_wrong_token_from_the_environment_is_reported(farm):
    done = _run(farm, "ls", env={"RENDERFARM_TOKEN": "rf_wrong"})
    assert done.returncode == 1 and "unknown API token" in done.stderr
    assert "[authorization]" in done.stderr

"""FarmService has no default caller: every job operation must be told who asks, so a handler
that forgets to pass the caller is refused instead of acting as the local admin."""

from __future__ import annotations

import asyncio
import inspect

import pytest

from renderfarm.app.auth import Caller
from renderfarm.app.composition import build_farm_service
from renderfarm.app.jobs import FarmService
from renderfarm.domain.jobspec import JobSettings
from renderfarm.infra.config import Settings

JOB = "0123456789ab"


class NoStore:
    """Any database call is a failure of the test: the refusal must come first."""

    def __getattr__(self, name):
        raise AssertionError(f"the store was used ({name}) before the caller was checked")


def _service(tmp_path) -> FarmService:
    service = build_farm_service(Settings(data_dir=tmp_path), NoStore())
    service.scheduler.add_job(JOB, JobSettings(width=16, height=16, tile_size=8), "0" * 64)
    service.owners[JOB] = "alice"
    return service


SUBMIT = dict(scene_data=None, scene_sha256="a" * 64, filename="", name="", raw_settings=None)

# Each public method that acts for a caller, with its other arguments.
CALLS = {
    "submit": ((), SUBMIT),
    "get": ((JOB,), {}),
    "list": ((None, 10, ""), {}),
    "cancel": ((JOB,), {}),
    "delete": ((JOB,), {}),
    "watch": ((JOB,), {}),
    "events": ((JOB,), {}),
    "frames": ((JOB,), {}),
    "frame_camera": ((JOB, 0), {}),
    "pixel_mattes": ((JOB, 0, 0, 0), {}),
    "image": ((JOB, "png", "rgb"), {}),
    "image_file": ((JOB, "png", "rgb"), {}),
    "movie_file": ((JOB,), {}),
    "convergence": ((JOB,), {}),
    "pause": ((JOB,), {}),
    "resume": ((JOB,), {}),
    "retry": ((JOB,), {}),
    "update": ((JOB,), {"priority": 5}),
    "continue_": ((JOB,), {"raw_settings": {"max_spp": 2048}}),
    "set_worker_mode": (("some-worker", "draining"), {}),
}


def _run(service: FarmService, name: str, args, kwargs):
    result = getattr(service, name)(*args, **kwargs)
    if inspect.isasyncgen(result):
        return asyncio.run(anext(result))
    return asyncio.run(result)


def test_every_method_that_acts_for_a_caller_is_listed():
    takes_caller = {
        name
        for name, method in inspect.getmembers(FarmService, inspect.isfunction)
        if not name.startswith("_") and "caller" in inspect.signature(method).parameters
    }
    assert takes_caller == set(CALLS)
    for name in CALLS:
        parameter = inspect.signature(getattr(FarmService, name)).parameters["caller"]
        assert parameter.default is inspect.Parameter.empty, f"{name} has a default caller"


@pytest.mark.parametrize("name", sorted(CALLS))
def test_a_missing_caller_is_refused(tmp_path, name):
    args, kwargs = CALLS[name]
    with pytest.raises(TypeError, match="caller"):
        _run(_service(tmp_path), name, args, kwargs)


@pytest.mark.parametrize("name", sorted(CALLS))
@pytest.mark.parametrize("bad", [None, "admin", {"owner": "", "admin": True}])
def test_a_caller_that_is_not_a_caller_is_refused(tmp_path, name, bad):
    args, kwargs = CALLS[name]
    with pytest.raises(TypeError, match="caller"):
        _run(_service(tmp_path), name, args, {**kwargs, "caller": bad})


def test_the_caller_given_is_the_one_checked(tmp_path):
    from renderfarm.errors import Forbidden

    service = _service(tmp_path)
    assert asyncio.run(service.get(JOB, Caller("alice", admin=False))).owner == "alice"
    with pytest.raises(Forbidden):
        asyncio.run(service.get(JOB, Caller("bob", admin=False)))

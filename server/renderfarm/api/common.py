"""Request checks shared by the REST and gRPC handlers, so both refuse the same input with the
same field named (tests/test_api_parity.py holds them to it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..domain.jobspec import check_sha256, check_text, is_job_id
from ..domain.scenes.bundles import scene_upload
from ..domain.scenes.usd_upload import usd_kind
from ..domain.states import JobState
from ..errors import NotFound, SettingsError

MAX_NAME = 200
MAX_PAGE_TOKEN = 200


@dataclass(frozen=True)
class Submission:
    """Checked arguments of FarmService.submit (except settings, which it parses itself)."""

    scene_data: bytes | None
    scene_sha256: str | None
    filename: str
    name: str
    environment_data: bytes | None
    environment_filename: str

    def kwargs(self) -> dict[str, Any]:
        return dict(self.__dict__)


def submission(
    *,
    scene_data: bytes | None,
    scene_sha256: str | None,
    filename: str,
    name: str,
    environment_data: bytes | None,
    environment_filename: str,
    max_upload_bytes: int,
) -> Submission:
    """Text fields free of control characters, a well-formed scene hash, and a .zip/.tar
    bundle packed into the .glb the workers will receive. A USD upload (a layer, a .usdz or a
    bundle of USD layers) is passed on as it is: the service converts it in a child process."""
    name = check_text("name", name, 10 * MAX_NAME)
    filename = check_text("scene_filename", filename, MAX_NAME)
    environment_filename = check_text("environment_filename", environment_filename, MAX_NAME)
    if scene_sha256:
        scene_sha256 = check_sha256("scene_sha256", scene_sha256)
    if scene_data is not None and scene_sha256:
        raise SettingsError("scene", "give either an uploaded scene or scene_sha256, not both")
    if usd_kind(scene_data, filename) is None:
        scene_data, filename = scene_upload(scene_data, filename, max_upload_bytes)
    return Submission(
        scene_data=scene_data,
        scene_sha256=scene_sha256 or None,
        filename=filename,
        name=name,
        environment_data=environment_data or None,
        environment_filename=environment_filename,
    )


def job_id(value: str) -> str:
    """A job id as given, or NotFound for one no job could have (never reaches the database)."""
    if not is_job_id(value):
        raise NotFound(f"no job with id {value[:80]!r}")
    return value


MAX_AFTER = 100


def after_ids(value: Any) -> list[str]:
    """The `after` field of a submission: job ids, as a list (JSON, gRPC) or a text of ids
    separated by commas or spaces (a form field). Whether the jobs exist is the service's
    question; it names `after` too."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise SettingsError("after", "after must be a list of job ids")
    if len(value) > MAX_AFTER:
        raise SettingsError("after", f"after names more than {MAX_AFTER} jobs")
    for v in value:
        if not is_job_id(v):
            raise SettingsError("after", f"after: no job with id {v[:80]!r}")
    return list(value)


def job_name(value: Any) -> str | None:
    """A new job name (an update): None leaves it as it is."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise SettingsError("name", "name must be text")
    return check_text("name", value, 10 * MAX_NAME)


def scene_sha256(value: str) -> str:
    return check_sha256("sha256", value)


def job_state(value: str) -> JobState | None:
    """A state filter ("" = every state)."""
    if not value:
        return None
    try:
        return JobState(value)
    except ValueError:
        states = ", ".join(s.value for s in JobState)
        raise SettingsError("state", f"unknown state {value[:40]!r}; one of {states}") from None


def page_token(value: str) -> str:
    return check_text("page_token", value, MAX_PAGE_TOKEN)


IMAGE_MEDIA_TYPES = {"png": "image/png", "exr": "image/x-exr"}

"""A job as the APIs show it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..domain.jobspec import JobSettings
from ..domain.states import JobState


@dataclass(frozen=True)
class ProgressView:
    tiles_total: int
    tiles_done: int
    tiles_previewed: int
    mean_spp: float
    error: float | None
    eta_s: float | None
    samples_merged: int
    elapsed_s: float
    frames_total: int = 1  # images the job renders: its frames, or 1 for a still
    frames_done: int = 0  # frames whose every tile has stopped


@dataclass(frozen=True)
class FrameView:
    """One frame of an animation job, or one variant of a job of every variant (its index as
    the frame number; GET /api/v1/jobs/{id}/frames)."""

    frame: int
    state: str  # "queued" (nothing merged yet), "rendering" or "done"
    tiles_total: int
    tiles_done: int
    mean_spp: float
    error: float | None  # RMS of its tiles' relative errors; None before any estimate
    variant: str | None = None  # the variant's name, for a job of every variant

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class JobView:
    """A job as the APIs show it (REST JSON and the gRPC Job message are built from this)."""

    id: str
    name: str
    state: JobState
    settings: JobSettings
    scene_sha256: str
    progress: ProgressView
    error: str
    created_unix_s: float
    finished_unix_s: float | None
    owner: str = ""
    after: tuple[str, ...] = ()  # ids of the jobs it waits for
    require_tags: tuple[str, ...] = ()  # only workers with all these tags render it
    # settings.variant "all": the scene's variants, one image each (not shown: the frame list
    # names each image's variant)
    variants: tuple[str, ...] = ()
    # The server (replica) that owns and renders it now; "" when none does (a finished job)
    replica: str = ""

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "state": self.state.value,
            "settings": self.settings.to_dict(),
            "scene_sha256": self.scene_sha256,
            "progress": self.progress.__dict__,
            "error": self.error,
            "created_unix_s": self.created_unix_s,
            "finished_unix_s": self.finished_unix_s,
            "owner": self.owner,
            "after": list(self.after),
            "require_tags": list(self.require_tags),
            "replica": self.replica,
        }


def finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None

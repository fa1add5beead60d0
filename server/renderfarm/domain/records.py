"""What the scheduler keeps, as records: results and leases of tasks, tiles, jobs, workers and
progress. The scheduler (scheduler.py) is the one that changes them."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .jobspec import JobSettings
from .merge import TileAccumulator
from .states import JobState, StopReason
from .tiling import Rect

ETA_MAX_POINTS = 4096  # merge records kept per job; a very busy job's window is just shorter


@dataclass(frozen=True)
class BatchResult:
    """One task's output as the scheduler needs it (decoded from a TileResult)."""

    job_id: str
    tile_index: int
    batch_index: int
    sample_start: int
    sample_count: int
    rect: Rect
    rgb_sum: np.ndarray
    luminance_m2: np.ndarray
    albedo_sum: np.ndarray | None = None
    normal_sum: np.ndarray | None = None
    nonfinite: int = 0
    render_seconds: float = 0.0
    rays: int = 0
    warnings: tuple[str, ...] = ()  # the worker's messages about the task (its scene's loader)
    coverage_sum: np.ndarray | None = None  # per pixel, samples whose camera ray hit geometry
    # The sums of the other rows of the channel table the task named (depth, position, ...), by
    # their wire name (channels.Channel.wire).
    extra: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Lease:
    task_id: str
    job_id: str
    tile_index: int
    batch_index: int
    sample_start: int
    sample_count: int
    rect: Rect
    worker_id: str
    deadline: float
    # Per-pixel adaptive sampling: the pixels the batch renders (workers.proto,
    # Task.active_pixels); empty: every pixel.
    active: bytes = b""
    # How many pixels the batch renders (the rect's, or the mask's).
    pixels: int = 0


@dataclass(frozen=True)
class StopRecord:
    tile_index: int
    batch_index: int  # last merged batch
    spp: int
    error: float
    reason: StopReason


@dataclass(frozen=True)
class Event:
    kind: str  # "job_started", "tile_stopped", "job_finished", "task_failed", "worker_excluded"
    job_id: str
    data: dict


@dataclass
class TileState:
    index: int
    rect: Rect
    acc: TileAccumulator
    next_batch: int = 0  # lowest batch never leased
    requeue: set[int] = field(default_factory=set)  # batches whose lease was lost
    in_flight: dict[int, str] = field(default_factory=dict)  # batch -> task id
    pending: dict[int, BatchResult] = field(default_factory=dict)  # arrived early
    stop: StopRecord | None = None
    error: float = math.inf
    seconds_per_sample: float = 0.0  # measured render cost per pixel sample
    slot: int = 0  # the frame's place in the job's frame list (0 for a still)
    dirty: bool = False  # merged since the last checkpoint
    aovs_dirty: bool = False  # albedo/normal sums changed since the last checkpoint
    stamp: int = 0  # bumped on every change; heap entries with an older stamp are stale
    # Samples per pixel of planned batches (index >= PLANNED_FROM), by batch index.
    plan: dict[int, int] = field(default_factory=dict)
    # What each planned batch was planned from, by batch index: (count, merged samples per
    # pixel, relative error or None when not finite, samples per pixel before the batch). A
    # continue replays the plans under its new settings (continue_plan).
    basis: dict[int, tuple[int, int, float | None, int]] = field(default_factory=dict)

    @property
    def merged(self) -> int:
        return self.acc.batches

    @property
    def stopped(self) -> bool:
        return self.stop is not None


@dataclass
class JobRun:
    job_id: str
    settings: JobSettings
    scene_sha256: str
    tiles: list[TileState]
    created: float
    state: JobState = JobState.QUEUED
    started: float | None = None
    finished: float | None = None
    leased: int = 0  # leases currently out (for fair share)
    error_message: str = ""
    excluded_workers: set[str] = field(default_factory=set)
    failures: dict[str, int] = field(default_factory=dict)  # worker -> failed tasks
    samples_merged: int = 0
    version: int = 0  # bumped on every visible change (watchers wait on it)
    tiles_stopped: int = 0
    # Dispatch candidates: (key, stamp, tile index), smallest key first; see Scheduler._touch.
    heap: list[tuple[tuple, int, int]] = field(default_factory=list)
    cost_sum: float = 0.0  # sum of the measured per-tile costs, for tiles not measured yet
    cost_count: int = 0
    # (clock, samples_merged after it) of each merged batch in the ETA window (see _eta).
    merges: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=ETA_MAX_POINTS))
    after: tuple[str, ...] = ()  # ids of the jobs it waits for (state WAITING until completed)
    paused_at: float | None = None  # clock when paused: the pause does not count as elapsed
    elapsed_before: float = 0.0  # elapsed seconds of earlier runs (restored, retried, continued)
    require_tags: frozenset[str] = frozenset()  # only workers with all of these take its tasks
    # What a worker must have to take its tasks: require_tags and the capability tags of the
    # rows of its layout beyond every job's (channels.capability_tags).
    requires: frozenset[str] = frozenset()
    # The numbers of its images: an animation's frames, the variants' indices for a job of
    # every variant (settings.variant "all"); None: a still.
    frames: tuple[int, ...] | None = None
    variants: tuple[str, ...] = ()  # the variants' names of a job of every variant, by index
    tiles_per_frame: int = 0
    frame_tiles_stopped: list[int] = field(default_factory=list)  # by slot
    # The task log (task_warning events): messages recorded once each, at most TASK_LOG_MAX.
    warnings_logged: set[str] = field(default_factory=set)

    @property
    def pixels(self) -> int:
        """Pixels of one frame."""
        return self.settings.width * self.settings.height

    @property
    def frame_count(self) -> int:
        return 1 if self.frames is None else len(self.frames)

    def frame_tiles(self, slot: int) -> list[TileState]:
        n = self.tiles_per_frame
        return self.tiles[slot * n : (slot + 1) * n]


@dataclass
class WorkerSlot:
    worker_id: str
    credit: int
    leases: dict[str, Lease] = field(default_factory=dict)
    tags: frozenset[str] = frozenset()  # announced in its Hello (--tag)
    # A lease of it ran out without a heartbeat (hung, stopped or cut off): it is leased
    # nothing more until its next heartbeat, so the batches handed back go to other workers.
    unresponsive: bool = False


# Operator modes of a worker (docs/operators.md): an active worker takes tasks; a draining one
# finishes the tasks it holds and takes no more; a disabled one has handed its tasks back.
WORKER_MODES = ("active", "draining", "disabled")

RECENT_ERRORS = 5  # error messages kept per worker
TASK_LOG_MAX = 100  # distinct worker warnings recorded per job run (task_warning events)


@dataclass
class WorkerRecord:
    """What the scheduler remembers of a worker id for the server's life, across reconnects
    (workers reconnect with the same id): the operator's mode and its task failures."""

    mode: str = "active"
    tasks_failed: int = 0
    errors: deque[str] = field(default_factory=lambda: deque(maxlen=RECENT_ERRORS))


@dataclass(frozen=True)
class FrameProgress:
    """One frame of an animation job (or one variant of a job of every variant)."""

    frame: int
    state: str  # "queued" (nothing merged), "rendering" or "done" (every tile stopped)
    tiles_total: int
    tiles_done: int
    mean_spp: float
    error: float  # RMS over its merged tiles of the tile relative error; inf before any
    variant: str | None = None  # the variant's name, for a job of every variant


@dataclass(frozen=True)
class Progress:
    tiles_total: int
    tiles_done: int
    tiles_previewed: int
    mean_spp: float
    error: float
    eta_s: float | None  # None until two batches have been merged (no rate yet)
    samples_merged: int
    elapsed_s: float
    frames_total: int = 1
    frames_done: int = 0

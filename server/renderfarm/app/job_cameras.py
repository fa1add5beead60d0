"""A job's camera data, image by image (docs/usage.md, "Camera data"): the camera the workers
render each frame through, as the workers' own loader poses it (SceneChecker.cameras runs
`renderfarm-worker camera` in a limited child process), turned into intrinsics and matrices by
domain/camera.py. Served as camera.json and written into the job's EXR header.

A frame of an animation is posed at its glTF time, frame / fps, by the animations
settings.animation selects, as the worker's task is (api/grpc_api.py, JobServicer._assign); a
still, and each image of a job of every variant (variants change materials, not the camera),
as the scene is stored. With motion blur the camera may move during the shutter: the data is
the frame's time's. The loader's answers are kept in memory per (job, frame); the frames of an
animation are posed CAMERA_BATCH at a time, one process for all of them.
"""

from __future__ import annotations

import asyncio
import json
from collections import OrderedDict
from typing import Any

from ..domain.camera import exr_matrices, frame_camera
from ..domain.frames import frame_slot, frame_time, job_frames, parse_shutter
from ..errors import NotFound
from .auth import Caller
from .views import JobView

CAMERA_BATCH = 16  # frames of an animation posed by one run of the loader
MAX_CACHED_CAMERAS = 4096  # (job, frame) poses kept, least recently used dropped first


class JobCameras:
    """Part of FarmService (jobs.py), whose __init__ sets _cameras and _camera_runs."""

    _cameras: OrderedDict[tuple[str, int | None], dict[str, Any]]
    _camera_runs: dict[tuple[str, int | None], asyncio.Future[dict[int | None, dict[str, Any]]]]

    async def frame_camera(self, job_id: str, frame: int | None, caller: Caller) -> dict[str, Any]:
        """camera.json of one image of the job: `frame` a frame of its animation, 0 for a still,
        a variant's index for a job of every variant (None: the first image). NotFound (field
        `frame`) for an image the job does not have, NotFound / Forbidden as get for the job."""
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        return await self._camera_of(view, frame_slot(view.settings, frame, view.variants))

    async def exr_camera_attributes(self, view: JobView, slot: int) -> dict[str, Any]:
        """The EXR header's camera attributes of image `slot` of the job: OpenEXR's standard
        worldToCamera and worldToNDC (M44f, as 16 floats: infra/images.py writes a 16-tuple
        as a matrix) and renderfarm:camera (camera.json)."""
        camera = await self._camera_of(view, slot)
        to_camera, to_ndc = exr_matrices(camera)
        return {
            "worldToCamera": to_camera,
            "worldToNDC": to_ndc,
            "renderfarm:camera": json.dumps(camera, sort_keys=True),
        }

    async def _camera_of(self, view: JobView, slot: int) -> dict[str, Any]:
        settings = view.settings
        numbers = job_frames(settings, view.variants)
        animated = bool(settings.frames)  # frames are posed; a still and variants are not
        frame = numbers[slot] if numbers is not None else 0
        key = frame if animated else None
        pose = self._cameras.get((view.id, key))
        if pose is not None:
            self._cameras.move_to_end((view.id, key))
        else:
            batch: tuple[int, ...] | None = None
            if animated and numbers is not None:
                start = slot - slot % CAMERA_BATCH
                batch = numbers[start : start + CAMERA_BATCH]
            run_key = (view.id, batch[0] if batch else None)
            run = self._camera_runs.get(run_key)
            if run is None:
                run = asyncio.ensure_future(self._pose_cameras(view, batch))
                self._camera_runs[run_key] = run
                run.add_done_callback(lambda _: self._camera_runs.pop(run_key, None))
            # Shielded: a request that goes away does not cancel the others' run.
            pose = (await asyncio.shield(run))[key]
        shutter_s = None
        time_s = frame_time(frame, settings.fps) if animated else None
        shutter = parse_shutter(settings.shutter) if animated else None
        if shutter is not None:
            shutter_s = (frame_time(frame + shutter[0], settings.fps),
                         frame_time(frame + shutter[1], settings.fps))  # fmt: skip
        return frame_camera(pose, settings.width, settings.height, frame, time_s, shutter_s)

    async def _pose_cameras(
        self, view: JobView, frames: tuple[int, ...] | None
    ) -> dict[int | None, dict[str, Any]]:
        """The loader's camera of each of `frames` (None: the still), remembered."""
        settings = view.settings
        info = await self.store.get_scene_info(view.scene_sha256)
        if info is None:
            raise NotFound(f"the scene of job {view.id} is no longer stored")
        data = await self.store.read_scene(view.scene_sha256, 0, int(info["size_bytes"]))
        times = None if frames is None else [frame_time(f, settings.fps) for f in frames]
        poses = await self.scene_checker.cameras(
            data, f"scene {view.scene_sha256[:12]}", times, settings.animation,
            settings.shutter, settings.fps,
        )  # fmt: skip
        keys: tuple[int | None, ...] = (None,) if frames is None else frames
        if len(poses) != len(keys):
            raise RuntimeError(f"the loader posed {len(poses)} cameras for {len(keys)} images")
        found = dict(zip(keys, poses, strict=True))
        for key, pose in found.items():
            self._cameras[(view.id, key)] = pose
        while len(self._cameras) > MAX_CACHED_CAMERAS:
            self._cameras.popitem(last=False)
        return found

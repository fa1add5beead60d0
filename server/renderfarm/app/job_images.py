"""A job's image (PNG or EXR, any layer) written to a scratch file a row of tiles at a time, from
memory while the job is held, else from its checkpoint in the database.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import json
import logging
import math
import os
import tempfile
from typing import Any, BinaryIO

from ..domain import channels, cryptomatte
from ..domain.channels import job_layout
from ..domain.frames import frame_slot, job_frames, job_rects, tiles_per_frame
from ..domain.jobspec import JobSettings
from ..domain.records import FrameProgress
from ..domain.scenes import metadata
from ..errors import NotFound, SceneError, SettingsError, TooLarge
from ..infra import images
from ..infra.store import TileSummary
from . import checkpoints
from .auth import Caller, check_caller
from .views import FrameView, JobView, finite_or_none

log = logging.getLogger(__name__)

MAX_IMAGE_SIZE = 1 << 16  # largest max_size of a PNG preview
# A .gltf scene (JSON throughout, its buffers as data: URIs) larger than this is not parsed for
# its KHR_xmp_json_ld metadata when an EXR is written; a GLB's JSON chunk always is.
MAX_METADATA_GLTF_BYTES = 64 << 20


class JobImages:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    async def _scene_json(self, sha256: str, max_gltf_bytes: int) -> bytes | None:
        """The stored scene's glTF JSON: a GLB's JSON chunk, or a .gltf of at most
        max_gltf_bytes whole; None if there is none (or it is larger)."""
        head = await self.store.read_scene(sha256, 0, metadata.JSON_CHUNK_OFFSET)
        if not head:
            return None
        length = metadata.json_chunk_length(head)
        if length is None:
            info = await self.store.get_scene_info(sha256)
            size = int(info["size_bytes"]) if info else 0
            if not 0 < size <= max_gltf_bytes:
                return None
            return await self.store.read_scene(sha256, 0, size)
        return await self.store.read_scene(sha256, metadata.JSON_CHUNK_OFFSET, length)

    async def _scene_xmp(self, sha256: str) -> str | None:
        """The stored scene's asset metadata (KHR_xmp_json_ld) for the EXR header, or None
        (domain/scenes/metadata.py)."""
        raw = await self._scene_json(sha256, MAX_METADATA_GLTF_BYTES)
        return None if raw is None else await asyncio.to_thread(metadata.xmp_attribute, raw)

    async def _crypto_names(self, sha256: str) -> cryptomatte.Names:
        """The scene's Cryptomatte names (domain/cryptomatte.py): its nodes' and materials'.
        A .gltf is read whole whatever its size (the upload limits bound it): the IDs are
        hashes of the names, so they cannot do without them."""
        raw = await self._scene_json(sha256, 1 << 62)
        if raw is None:
            raise NotFound(f"scene {sha256} is gone: its Cryptomatte names are unknown")
        return await asyncio.to_thread(cryptomatte.names_of_json, raw)

    async def image_file(
        self,
        job_id: str,
        fmt: str,
        layer: str,
        caller: Caller,
        max_size: int = 0,
        compression: str = "zip",
        frame: int | None = None,
        _denoise_turn_held: bool = False,
        group: str = "",
    ) -> BinaryIO:
        """The image written to a scratch file, returned open for reading (the file is
        already unlinked: closing it frees the space). Written one row of tiles at a time
        (images.ImageWriter), from memory while the job is held, else from the database.

        frame: which frame of an animation, or the index of a variant of a job of every variant
        (None: the first, or the still); NotFound when the job does not render it.
        group: the light group a PNG of the light_group layer shows (empty: the first)."""
        check_caller(caller)
        if fmt not in ("png", "exr"):
            raise SettingsError("format", f"unknown image format {fmt!r}; use png or exr")
        if layer not in images.LAYERS:
            raise SettingsError(
                "layer", f"unknown layer {layer!r}; one of {', '.join(images.LAYERS)}"
            )
        if not 0 <= max_size <= MAX_IMAGE_SIZE:
            raise SettingsError("max_size", f"max_size must be in 0..{MAX_IMAGE_SIZE}")
        if compression not in images.EXR_COMPRESSIONS:
            raise SettingsError(
                "compression",
                f"unknown compression {compression[:40]!r}; one of "
                f"{', '.join(images.EXR_COMPRESSIONS)}",
            )
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        job = self.scheduler.jobs.get(job_id)
        row = await self.store.get_job(job_id)
        if row is None:
            raise NotFound(f"no job with id {job_id!r}")
        settings = job.settings if job is not None else JobSettings(**row.settings)
        variants = tuple(row.variants)
        layout = job_layout(settings)
        if group and (fmt != "png" or layer != channels.LIGHT_GROUP_LAYER):
            raise SettingsError("group", "group picks a light group of a PNG of light_group")
        if fmt == "png" and layer == channels.LIGHT_GROUP_LAYER and layout.groups:
            group = group or layout.groups[0]
            if group not in layout.groups:
                raise SettingsError(
                    "group",
                    f"job {job_id} has no light group {group[:60]!r}; its groups: "
                    f"{', '.join(layout.groups)}",
                )
            layer = channels.group_layer(group)
        if fmt == "png" and layer not in layout.layers():
            row = channels.layer_channel(layer)
            turned_on = f"settings.aovs naming {row.aov}" if row.aov else f"settings.{row.setting}"
            raise SettingsError(
                "layer",
                f"job {job_id} was submitted without {turned_on}: it has no {layer} layer",
            )
        if settings.denoise and (fmt == "exr" or layer == "denoised") and not _denoise_turn_held:
            async with self._denoise_turn:
                return await self.image_file(
                    job_id, fmt, layer, caller, max_size, compression, frame,
                    _denoise_turn_held=True, group=group,
                )  # fmt: skip
        # The EXR's DateTime: when the job finished (when it was submitted while it runs).
        stamp = (row.finished_at or row.created_at).timestamp()
        slot = frame_slot(settings, frame, variants)
        rects = job_rects(settings, variants)  # of every frame; this frame's start at `base`
        base = slot * tiles_per_frame(settings)
        cols = math.ceil(settings.width / settings.tile_size)
        rows = tiles_per_frame(settings) // cols
        names = images.arrays_needed(fmt, layer, layout)

        async def band(r: int) -> images.Band:
            """Row r of tiles with their arrays (read in a thread: from RAM, a spill file or
            the database)."""
            live = self.scheduler.jobs.get(job_id)
            if live is not None:  # snapshots on the loop (cheap), arrays read in the thread
                first = base + r * cols
                views = [(t.rect, images.TileView.of(t.rect, t.acc, names)) for t in
                         live.tiles[first : first + cols]]  # fmt: skip
                return await asyncio.to_thread(
                    lambda: [(rect, v and v.accumulator()) for rect, v in views]
                )
            stored = await self.store.load_tiles(job_id, first=base + r * cols, count=cols)
            if not stored and await self.store.get_job(job_id) is None:
                raise NotFound(f"no job with id {job_id!r}")  # deleted meanwhile
            return await asyncio.to_thread(
                checkpoints.band_from_rows, settings, rects, base + r * cols, cols, stored
            )

        top = 1.0
        if fmt == "png" and layer in images.SCALED_LAYERS:  # a pass for the maximum
            top = -math.inf
            for r in range(rows):
                top = max(top, await asyncio.to_thread(images.layer_maximum, layer, await band(r)))
        denoised = None
        if settings.denoise and (fmt == "exr" or layer == "denoised"):
            # A first pass gathers the frame Open Image Denoise needs whole (infra/images.py).
            whole = images.DenoiseFrame(settings.width, settings.height)
            for r in range(rows):
                await asyncio.to_thread(whole.add_band, rects[r * cols].height, await band(r))
            denoised = await asyncio.to_thread(whole.denoise)
            del whole
        attributes: dict[str, Any] | None = None
        if fmt == "exr":
            numbers = job_frames(settings, variants)
            # The upload submitted with this job; else (submitted by scene_sha256) the scene's.
            source = await self.store.get_job_scene_source(view.id)
            if source is None:
                source = await self.store.get_scene_source(view.scene_sha256)
            if variants:  # its variant's index and name rather than a frame number
                attributes = exr_attributes(view, None, source, (slot, variants[slot]))
            else:
                frame_number = None if numbers is None else numbers[slot]
                attributes = exr_attributes(view, frame_number, source)
            xmp = await self._scene_xmp(view.scene_sha256)
            if xmp is not None:
                attributes["renderfarm:xmp_json_ld"] = xmp
            try:  # worldToCamera, worldToNDC and renderfarm:camera (job_cameras.py)
                attributes.update(await self.exr_camera_attributes(view, slot))
            except (SceneError, NotFound) as e:  # the loader refused the scene now, or it is
                # gone: the image without them
                log.warning("job %s: no camera data in its EXR: %s", job_id, e.message)
        crypto = None
        ranked = [c for c in layout.rows if c.accumulate is channels.Accumulate.RANKED]
        if ranked and (fmt == "exr" or any(layer == la.name for c in ranked for la in c.layers)):
            crypto = await self.cached_crypto_names(view.scene_sha256)
        scratch = self.scheduler.cache.directory
        scratch.mkdir(parents=True, exist_ok=True)
        fd, path = tempfile.mkstemp(suffix=f".{fmt}", dir=scratch)
        os.close(fd)
        writer = None
        try:
            writer = await asyncio.to_thread(
                images.ImageWriter, path, fmt, settings.width, settings.height, layer, max_size,
                top, self._stopping, compression, stamp, denoised, attributes, layout, crypto,
            )  # fmt: skip
            for r in range(rows):
                tiles = await band(r)
                await asyncio.to_thread(
                    writer.write_band, rects[r * cols].height, tiles, r == rows - 1
                )
            await asyncio.to_thread(writer.close)
            f = open(path, "rb")  # noqa: SIM115 (the caller closes it)
        except BaseException:
            # The writer may still be in its thread (this task was cancelled while it wrote a
            # band): close and remove it there, after that band, without waiting here.
            asyncio.get_running_loop().run_in_executor(None, _discard_image, writer, path)
            raise
        os.unlink(path)
        return f

    async def frames(self, job_id: str, caller: Caller) -> list[FrameView]:
        """Every frame of the job with its progress (one, frame 0, for a still; a job of every
        variant has one per variant, numbered by its index and named): from memory while the
        job is held, else from its stored tiles."""
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        settings, variants = view.settings, view.variants
        numbers = job_frames(settings, variants) or (0,)
        live = self.scheduler.jobs.get(job_id)
        if live is not None:
            return [
                _frame_view(self.scheduler.frame_progress(live, slot))
                for slot in range(len(numbers))
            ]
        per_frame = tiles_per_frame(settings)
        rects = job_rects(settings, variants)
        slots: list[list[TileSummary]] = [[] for _ in numbers]
        for t in await self.store.tile_summaries(job_id):
            if 0 <= t.tile_index < len(rects):
                slots[t.tile_index // per_frame].append(t)
        views = []
        for frame, tiles in zip(numbers, slots, strict=True):
            errors = [t.error for t in tiles if t.samples > 0 and t.error is not None]
            done = sum(1 for t in tiles if t.stopped)
            views.append(FrameView(
                frame=frame,
                state="done" if done == per_frame else ("rendering" if errors else "queued"),
                tiles_total=per_frame,
                tiles_done=done,
                mean_spp=sum(t.samples * rects[t.tile_index].pixels for t in tiles)
                / (settings.width * settings.height),
                error=math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None,
                variant=variants[frame] if variants else None,
            ))  # fmt: skip
        return views

    async def image(
        self,
        job_id: str,
        fmt: str,
        layer: str,
        caller: Caller,
        max_size: int = 0,
        max_bytes: int | None = None,
        compression: str = "zip",
        frame: int | None = None,
        group: str = "",
    ) -> bytes:
        """The image as bytes (for gRPC's one message); TooLarge past max_bytes."""
        with await self.image_file(
            job_id, fmt, layer, caller, max_size, compression, frame, group=group
        ) as f:
            size = os.fstat(f.fileno()).st_size
            if max_bytes is not None and size > max_bytes:
                raise TooLarge(
                    "format",
                    f"the {fmt} image is {size} bytes, more than one message may hold "
                    f"({max_bytes}); GET /api/v1/jobs/{job_id}/image.{fmt} streams it",
                )
            return await asyncio.to_thread(f.read)


def _frame_view(p: FrameProgress) -> FrameView:
    return FrameView(
        frame=p.frame, state=p.state, tiles_total=p.tiles_total, tiles_done=p.tiles_done,
        mean_spp=p.mean_spp, error=finite_or_none(p.error), variant=p.variant,
    )  # fmt: skip


def renderer_version() -> str:
    """The renderfarm release that rendered a job (the server's package; workers are built
    from the same release and report it in their hello)."""
    try:
        return importlib.metadata.version("renderfarm")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def exr_attributes(
    view: JobView,
    frame: int | None = None,
    source: dict[str, Any] | None = None,
    variant: tuple[int, str] | None = None,
) -> dict[str, str | float]:
    """The job's record in its EXR header (docs/usage.md, "Outputs"; its camera is added by
    job_cameras.py, exr_camera_attributes): its settings as JSON, scene,
    renderer version, mean spp and estimated error (absent while unknown), for a frame of an
    animation its number, for a variant of a job of every variant its index and name
    (`variant`), and for a scene converted at upload (USD) the source it was converted
    from (`source`: the store's scene source). No wall-clock time: the EXR stays a function of
    the job."""
    attributes: dict[str, str | float] = {
        "renderfarm:settings": json.dumps(view.settings.to_dict(), sort_keys=True),
        "renderfarm:scene_sha256": view.scene_sha256,
        "renderfarm:version": renderer_version(),
        "renderfarm:mean_spp": float(view.progress.mean_spp),
    }
    if view.progress.error is not None:
        attributes["renderfarm:error"] = float(view.progress.error)
    if frame is not None:
        attributes["renderfarm:frame"] = float(frame)
    if variant is not None:
        attributes["renderfarm:variant_index"] = float(variant[0])
        attributes["renderfarm:variant"] = variant[1]
    if source:
        attributes["renderfarm:scene_source_format"] = str(source["source_format"])
        attributes["renderfarm:scene_source_sha256"] = str(source["source_sha256"])
        attributes["renderfarm:scene_source_filename"] = str(source["source_filename"])
    return attributes


def _discard_image(writer: images.ImageWriter | None, path: str) -> None:
    if writer is not None:
        with contextlib.suppress(Exception):
            writer.abandon()
    with contextlib.suppress(OSError):
        os.unlink(path)

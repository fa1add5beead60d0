"""gRPC services (grpc.aio, same event loop as REST): JobService, SceneService, WorkerService.

Handlers parse, call FarmService and map its errors to status codes:
SettingsError/SceneError -> INVALID_ARGUMENT, TooLarge -> RESOURCE_EXHAUSTED,
NotFound -> NOT_FOUND, Conflict -> FAILED_PRECONDITION, AuthError/Unauthenticated ->
UNAUTHENTICATED, Forbidden -> PERMISSION_DENIED, DatabaseUnavailable -> UNAVAILABLE (with the
trailing metadata `retry-after`, seconds, like REST's 503 and 429). The details read
"FIELD: message" and the trailing metadata `renderfarm-field` names the field, like the REST
body's "field".

Clients authenticate with the metadata `authorization: Bearer TOKEN` (JobService,
SceneService.GetScene); workers with Hello.token. SceneService.FetchScene is open to anyone who
knows a scene's full SHA-256 (workers call it without client tokens).

One module: the three servicers share the error mapping and the caller lookup above them, and
each method is a thin translation of one proto rpc.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from ..app.auth import Authenticator, Caller
from ..app.jobs import FarmService
from ..app.views import JobView
from ..app.worker_sessions import WorkerSession
from ..domain import channels
from ..domain.frames import frame_time
from ..domain.jobspec import SETTINGS, check_tags
from ..domain.states import JobState
from ..domain.tiling import carries_aovs
from ..errors import (
    AuthError,
    Cancelled,
    Conflict,
    Forbidden,
    NotFound,
    SceneError,
    SettingsError,
    TooLarge,
    Unauthenticated,
)
from ..infra.store import DatabaseUnavailable
from ..v1 import jobs_pb2, jobs_pb2_grpc, scenes_pb2, scenes_pb2_grpc, workers_pb2, workers_pb2_grpc
from . import common as apicommon
from .grpc_decode import decode_result
from .sessions import bearer

log = logging.getLogger(__name__)

MAX_MESSAGE_BYTES = 512 * 2**20
# Leases sent in one ServerMessage.assigns at most (a worker's credit is at most 256).
MAX_PACKED_ASSIGNS = 64
_NOTHING = object()  # Connect's outbox loop: no message held back
# Past the last window's end, every batch carries the same channels.
_WINDOW_END = max(c.window for c in channels.CHANNELS)


@functools.cache
def _task_channels(layout: channels.Layout, sample_start_in_window: int) -> tuple[str, ...]:
    return tuple(c.name for c in layout.wire_rows_for(sample_start_in_window))


def _task_channels_for(settings, sample_start: int) -> tuple[str, ...]:
    """Task.channels of a batch: the rows of the job's layout whose window holds it (cached
    by the only things that matter, the layout and whether the batch starts inside each
    window)."""
    return _task_channels(channels.job_layout(settings), min(sample_start, _WINDOW_END))


def _enum_prefix(setting) -> str:
    """SAMPLER_ for settings.sampler: the proto enum's value names are PREFIX + VALUE.upper()."""
    return setting.name.upper() + "_"


def settings_to_proto(settings) -> jobs_pb2.RenderSettings:
    """A job's settings (the table, jobspec.SETTINGS) as the message: enumerations as their
    proto values, fields under their proto names."""
    values = {}
    for setting in SETTINGS:
        value = getattr(settings, setting.name)
        if setting.choices:
            value = (
                jobs_pb2.DESCRIPTOR.enum_types_by_name[setting.kind.__name__]
                .values_by_name[_enum_prefix(setting) + value.upper()]
                .number
            )
        values[setting.field] = value
    return jobs_pb2.RenderSettings(**values)


def settings_from_proto(msg: jobs_pb2.RenderSettings) -> dict:
    """The settings a request set (fields are proto3 `optional`: unset means the default, as
    does an enumeration's UNSPECIFIED). A number the enumeration does not have is passed on as
    text, for parse_settings to refuse naming the setting."""
    values: dict = {}
    for setting in SETTINGS:
        if not msg.HasField(setting.field):
            continue
        value = getattr(msg, setting.field)
        if setting.choices:
            if value == 0:
                continue
            enum = jobs_pb2.DESCRIPTOR.enum_types_by_name[setting.kind.__name__]
            known = enum.values_by_number.get(value)
            value = known.name.removeprefix(_enum_prefix(setting)).lower() if known else str(value)
        values[setting.name] = value
    return values


def job_to_proto(view: JobView) -> jobs_pb2.Job:
    p = view.progress
    s = view.settings
    return jobs_pb2.Job(
        id=view.id,
        name=view.name,
        state=jobs_pb2.JobState.Value(view.state.proto_name),
        settings=settings_to_proto(s),
        scene_sha256=view.scene_sha256,
        progress=jobs_pb2.JobProgress(
            tiles_total=p.tiles_total,
            tiles_done=p.tiles_done,
            tiles_previewed=p.tiles_previewed,
            mean_spp=p.mean_spp,
            error=p.error if p.error is not None else -1.0,
            eta_s=p.eta_s if p.eta_s is not None else -1.0,
            samples_merged=p.samples_merged,
            elapsed_s=p.elapsed_s,
            frames_total=p.frames_total,
            frames_done=p.frames_done,
        ),
        error=view.error,
        created_unix_s=view.created_unix_s,
        finished_unix_s=view.finished_unix_s or 0.0,
        owner=view.owner,
        after=list(view.after),
        require_tags=list(view.require_tags),
        replica=view.replica,
    )


def _status(e: Exception) -> tuple[grpc.StatusCode, str, str] | None:
    """(code, details, field) of an error FarmService or the checks raise; None: not ours."""
    if isinstance(e, (SettingsError, SceneError)):
        return grpc.StatusCode.INVALID_ARGUMENT, f"{e.field}: {e}", e.field
    if isinstance(e, TooLarge):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, f"{e.field}: {e.message}", e.field
    if isinstance(e, NotFound):
        return grpc.StatusCode.NOT_FOUND, e.message, e.field
    if isinstance(e, Conflict):
        return grpc.StatusCode.FAILED_PRECONDITION, e.message, ""
    if isinstance(e, AuthError):
        return grpc.StatusCode.UNAUTHENTICATED, e.message, "authorization"
    if isinstance(e, Forbidden):
        return grpc.StatusCode.PERMISSION_DENIED, e.message, "job_id"
    if isinstance(e, DatabaseUnavailable):
        return grpc.StatusCode.UNAVAILABLE, f"database: {e.message}", "database"
    return None


_API_ERRORS = (
    SettingsError, SceneError, TooLarge, NotFound, Conflict, AuthError, Forbidden,
    DatabaseUnavailable,
)  # fmt: skip


async def _abort(context, e: Exception) -> None:
    code, details, field = _status(e)
    metadata = [("renderfarm-field", field)]
    if isinstance(e, DatabaseUnavailable):
        metadata.append(("retry-after", str(e.retry_after_s)))
    await context.abort(code, details, trailing_metadata=tuple(metadata))


def _maps_errors(method):
    @functools.wraps(method)
    async def wrapper(self, request, context):
        try:
            return await method(self, request, context)
        except _API_ERRORS as e:
            await _abort(context, e)

    return wrapper


def _image_format(value: int) -> str:
    return "exr" if value == jobs_pb2.IMAGE_FORMAT_EXR else "png"


async def _caller(auth: Authenticator, context) -> Caller:
    metadata = dict(context.invocation_metadata() or ())
    return await auth.caller(bearer(metadata.get("authorization")))


class JobServicer(jobs_pb2_grpc.JobServiceServicer):
    def __init__(self, farm: FarmService, auth: Authenticator):
        self.farm = farm
        self.auth = auth

    @_maps_errors
    async def SubmitJob(self, request, context):  # noqa: N802 (gRPC method names)
        who = await _caller(self.auth, context)
        which = request.WhichOneof("scene")
        checked = apicommon.submission(
            scene_data=request.scene_data if which == "scene_data" else None,
            scene_sha256=request.scene_sha256 if which == "scene_sha256" else None,
            filename=request.scene_filename,
            name=request.name,
            environment_data=request.environment_data or None,
            environment_filename=request.environment_filename,
            max_upload_bytes=self.farm.settings.max_upload_bytes,
        )
        view = await self.farm.submit(
            **checked.kwargs(),
            raw_settings=settings_from_proto(request.settings),
            after=apicommon.after_ids(list(request.after)),
            caller=who,
            require_tags=check_tags("require_tags", list(request.require_tags)),
        )
        if self.farm.metrics is not None:
            self.farm.metrics.jobs_submitted.inc()
        return jobs_pb2.SubmitJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def GetJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.get(apicommon.job_id(request.job_id), who)
        return jobs_pb2.GetJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def ListJobs(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        state = None
        if request.state != jobs_pb2.JOB_STATE_UNSPECIFIED:
            try:
                name = jobs_pb2.JobState.Name(request.state)
            except ValueError:
                raise SettingsError("state", f"unknown state {request.state}") from None
            state = JobState(name[len("JOB_STATE_") :].lower())
        views, token = await self.farm.list(
            state, request.page_size, apicommon.page_token(request.page_token), caller=who
        )
        return jobs_pb2.ListJobsResponse(
            jobs=[job_to_proto(v) for v in views], next_page_token=token
        )

    @_maps_errors
    async def CancelJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.cancel(apicommon.job_id(request.job_id), who)
        return jobs_pb2.CancelJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def PauseJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.pause(apicommon.job_id(request.job_id), who)
        return jobs_pb2.PauseJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def ResumeJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.resume(apicommon.job_id(request.job_id), who)
        return jobs_pb2.ResumeJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def RetryJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.retry(apicommon.job_id(request.job_id), who)
        return jobs_pb2.RetryJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def UpdateJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        view = await self.farm.update(
            apicommon.job_id(request.job_id),
            who,
            priority=request.priority if request.HasField("priority") else None,
            name=apicommon.job_name(request.name) if request.HasField("name") else None,
        )
        return jobs_pb2.UpdateJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def ContinueJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        raw = settings_from_proto(request.settings)
        view = await self.farm.continue_(apicommon.job_id(request.job_id), who, raw)
        return jobs_pb2.ContinueJobResponse(job=job_to_proto(view))

    @_maps_errors
    async def DeleteJob(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        await self.farm.delete(apicommon.job_id(request.job_id), who)
        return jobs_pb2.DeleteJobResponse()

    @_maps_errors
    async def GetImage(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        fmt = _image_format(request.format)
        try:
            data = await self.farm.image(
                apicommon.job_id(request.job_id), fmt, request.layer or "rgb", who,
                max_size=request.max_size, max_bytes=MAX_MESSAGE_BYTES - (1 << 20),
                compression=request.compression or "zip",
                frame=request.frame if request.HasField("frame") else None,
                group=request.group,
            )  # fmt: skip
        except Cancelled:
            await context.abort(grpc.StatusCode.UNAVAILABLE, "the server is stopping")
        return jobs_pb2.GetImageResponse(
            data=data,
            format=jobs_pb2.IMAGE_FORMAT_EXR if fmt == "exr" else jobs_pb2.IMAGE_FORMAT_PNG,
            media_type=apicommon.IMAGE_MEDIA_TYPES[fmt],
        )

    @_maps_errors
    async def ListFrames(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        frames = await self.farm.frames(apicommon.job_id(request.job_id), who)
        return jobs_pb2.ListFramesResponse(
            frames=[
                jobs_pb2.FrameStatus(
                    frame=f.frame,
                    state=f.state,
                    tiles_total=f.tiles_total,
                    tiles_done=f.tiles_done,
                    mean_spp=f.mean_spp,
                    error=f.error if f.error is not None else -1.0,
                    variant=f.variant,
                )  # fmt: skip
                for f in frames
            ]
        )

    @_maps_errors
    async def GetFrameCamera(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        c = await self.farm.frame_camera(
            apicommon.job_id(request.job_id),
            request.frame if request.HasField("frame") else None,
            who,
        )
        return jobs_pb2.GetFrameCameraResponse(camera=frame_camera_to_proto(c))

    @_maps_errors
    async def GetPixelMattes(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        m = await self.farm.pixel_mattes(
            apicommon.job_id(request.job_id), request.x, request.y,
            request.frame if request.HasField("frame") else None, who,
        )  # fmt: skip
        return jobs_pb2.GetPixelMattesResponse(
            x=m["x"], y=m["y"], samples=m["samples"],
            **{key: [jobs_pb2.Matte(**e) for e in m[key]]
               for key in ("objects", "materials", "assets")},
        )  # fmt: skip

    @_maps_errors
    async def ListWorkers(self, request, context):  # noqa: N802
        await _caller(self.auth, context)
        return jobs_pb2.ListWorkersResponse(
            workers=[jobs_pb2.WorkerStatus(**w) for w in self.farm.workers()]
        )

    @_maps_errors
    async def ListReplicas(self, request, context):  # noqa: N802
        await _caller(self.auth, context)
        return jobs_pb2.ListReplicasResponse(
            replicas=[
                jobs_pb2.ReplicaStatus(
                    id=r["id"],
                    addresses=r["addresses"],
                    started_unix_s=r["started_unix_s"] or 0.0,
                    heartbeat_unix_s=r["heartbeat_unix_s"],
                    live=r["live"],
                    jobs_owned=r["jobs_owned"],
                    batches_merged=r["batches_merged"],
                    merge_rate=r["merge_rate"] or 0.0,
                )  # fmt: skip
                for r in await self.farm.replicas()
            ]
        )

    @_maps_errors
    async def SetWorkerMode(self, request, context):  # noqa: N802
        who = await _caller(self.auth, context)
        modes = {
            jobs_pb2.WORKER_MODE_ACTIVE: "active",
            jobs_pb2.WORKER_MODE_DRAINING: "draining",
            jobs_pb2.WORKER_MODE_DISABLED: "disabled",
        }
        if request.mode not in modes:
            raise SettingsError("mode", "mode must be ACTIVE, DRAINING or DISABLED")
        worker = await self.farm.set_worker_mode(request.worker_id, modes[request.mode], who)
        return jobs_pb2.SetWorkerModeResponse(worker=jobs_pb2.WorkerStatus(**worker))

    async def WatchJob(self, request, context):  # noqa: N802
        try:
            who = await _caller(self.auth, context)
            async for view in self.farm.watch(apicommon.job_id(request.job_id), who):
                yield jobs_pb2.WatchJobResponse(job=job_to_proto(view))
        except _API_ERRORS as e:
            await _abort(context, e)


class SceneServicer(scenes_pb2_grpc.SceneServiceServicer):
    def __init__(self, farm: FarmService, auth: Authenticator):
        self.farm = farm
        self.auth = auth

    @staticmethod
    def _info(info: dict) -> scenes_pb2.SceneInfo:
        fmt = {
            "glb": scenes_pb2.SCENE_FORMAT_GLB,
            "gltf": scenes_pb2.SCENE_FORMAT_GLTF,
            "hdr": scenes_pb2.SCENE_FORMAT_HDR,
            "exr": scenes_pb2.SCENE_FORMAT_EXR,
        }[info["format"]]
        return scenes_pb2.SceneInfo(
            sha256=info["sha256"],
            size_bytes=info["size_bytes"],
            format=fmt,
            filename=info["filename"],
        )

    async def FetchScene(self, request, context):  # noqa: N802
        try:
            info = await self.farm.scene_info(request.sha256)
            first = True
            async for offset, data in self.farm.scene_chunks(request.sha256):
                chunk = scenes_pb2.SceneChunk(offset=offset, data=data)
                if first:
                    chunk.info.CopyFrom(self._info(info))
                    first = False
                yield chunk
        except NotFound as e:
            await context.abort(grpc.StatusCode.NOT_FOUND, e.message)
        except DatabaseUnavailable as e:
            await _abort(context, e)

    @_maps_errors
    async def GetScene(self, request, context):  # noqa: N802
        await _caller(self.auth, context)
        info = await self.farm.scene_info(apicommon.scene_sha256(request.sha256))
        return scenes_pb2.GetSceneResponse(scene=self._info(info))


class WorkerServicer(workers_pb2_grpc.WorkerServiceServicer):
    def __init__(self, farm: FarmService):
        self.farm = farm
        self._settings_cache: dict[str, jobs_pb2.RenderSettings] = {}

    async def Connect(self, request_iterator, context):  # noqa: N802
        first = await anext(request_iterator.__aiter__(), None)
        if first is None or first.WhichOneof("msg") != "hello":
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, "send Hello first")
        hello = first.hello
        try:
            session = await self.farm.worker_hello(
                hello.worker_id,
                hello.hostname,
                hello.cores,
                hello.max_in_flight,
                hello.version,
                hello.token,
                check_tags("tags", list(hello.tags)),
                [name[:64] for name in hello.channels[:64]],
            )
        except Unauthenticated as e:
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, str(e))
        except SettingsError as e:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, e.message)
        settings = self.farm.settings
        yield workers_pb2.ServerMessage(
            welcome=workers_pb2.Welcome(
                worker_id=session.worker_id,
                heartbeat_interval_ms=int(settings.heartbeat_interval_s * 1000),
                lease_ms=int(settings.lease_s * 1000),
                packed=True,
            )
        )
        reader = asyncio.create_task(self._read(session, request_iterator))
        outbox, held = session.outbox, _NOTHING  # held: taken from the outbox, not sent yet
        try:
            while True:
                if held is not _NOTHING:
                    item, held = held, _NOTHING
                elif not outbox.empty():  # no waiting task needed for queued messages
                    item = outbox.get_nowait()
                else:
                    getter = asyncio.create_task(outbox.get())
                    done, _ = await asyncio.wait(
                        {getter, reader}, return_when=asyncio.FIRST_COMPLETED
                    )
                    if getter not in done:
                        getter.cancel()
                        break  # the worker closed its side or the stream broke
                    item = getter.result()
                if item is None:
                    break  # replaced by a newer connection, or the server is stopping
                if item[0] != "assign" or not hello.packed or outbox.empty():
                    yield self._message(item)
                    continue
                # A worker that reads packed messages gets the leases queued together in one.
                assigns = [self._assign(item)]
                while len(assigns) < MAX_PACKED_ASSIGNS and not outbox.empty():
                    item = outbox.get_nowait()
                    if item is None or item[0] != "assign":
                        held = item  # sent next, after these
                        break
                    assigns.append(self._assign(item))
                yield workers_pb2.ServerMessage(assigns=workers_pb2.Assigns(assigns=assigns))
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await reader
            await self.farm.worker_gone(session)

    def _settings_proto(self, job) -> jobs_pb2.RenderSettings:
        """A job's settings as a message, built once per job (a job's settings never change)."""
        cached = self._settings_cache.get(job.job_id)
        if cached is None:
            cached = self._settings_cache[job.job_id] = settings_to_proto(job.settings)
            while len(self._settings_cache) > 256:  # oldest first: dicts keep insertion order
                del self._settings_cache[next(iter(self._settings_cache))]
        return cached

    def _message(self, item) -> workers_pb2.ServerMessage:
        if item[0] == "cancel":
            return workers_pb2.ServerMessage(cancel=workers_pb2.Cancel(task_ids=item[1]))
        return workers_pb2.ServerMessage(assign=self._assign(item))

    def _assign(self, item) -> workers_pb2.Assign:
        _, lease, job = item
        if self.farm.metrics is not None:
            self.farm.metrics.tasks_assigned.inc()
        task = workers_pb2.Task(
            task_id=lease.task_id,
            job_id=lease.job_id,
            scene_sha256=job.scene_sha256,
            tile_index=lease.tile_index,
            rect=workers_pb2.TileRect(
                x0=lease.rect.x0, y0=lease.rect.y0, width=lease.rect.width, height=lease.rect.height
            ),
            batch_index=lease.batch_index,
            sample_start=lease.sample_start,
            skip_aovs=not carries_aovs(lease.sample_start),
            sample_count=lease.sample_count,
            channels=_task_channels_for(job.settings, lease.sample_start),
            active_pixels=lease.active,
        )
        task.settings.CopyFrom(self._settings_proto(job))
        if job.variants:  # a job of every variant: a still of the tile's variant, by index
            task.settings.variant = str(lease.tile_index // job.tiles_per_frame)
        elif job.frames is not None:  # a frame of an animation: posed at its glTF time
            frame = job.frames[lease.tile_index // job.tiles_per_frame]
            task.animated = True
            task.frame = frame
            task.time_s = frame_time(frame, job.settings.fps)
        return workers_pb2.Assign(task=task, lease_deadline_unix_ms=int(lease.deadline * 1000))

    async def _read(self, session: WorkerSession, request_iterator) -> None:
        async for msg in request_iterator:
            kind = msg.WhichOneof("msg")
            if kind in ("result", "results"):  # one, or several (workers.proto, TileResults)
                results = []
                for one in [msg.result] if kind == "result" else msg.results.results:
                    try:
                        results.append((one.task_id, decode_result(one)))
                    except ValueError as e:
                        log.warning("malformed result from %s: %s", session.worker_id, e)
                if results:
                    await self.farm.worker_results(session, results)
            elif kind == "heartbeat":
                hb = msg.heartbeat
                await self.farm.worker_heartbeat(
                    session, hb.samples_per_s, hb.rays_per_s, hb.busy_threads, hb.max_in_flight
                )
            elif kind == "failed":
                f = msg.failed
                if self.farm.metrics is not None:
                    self.farm.metrics.tasks_failed.labels(str(bool(f.retryable)).lower()).inc()
                await self.farm.worker_failed(session, f.task_id, f.error, f.retryable)


def frame_camera_to_proto(c: dict) -> jobs_pb2.FrameCamera:
    """camera.json (domain/camera.py) as its message: matrices flattened row by row, the
    nulls unset."""
    flat = {k: [v for row in c[k] for v in row] for k in ("world_to_camera", "camera_to_world")}
    same = ("frame", "projection", "width", "height", "fx", "fy", "cx", "cy", "convention", "near")
    optional = ("time_s", "yfov", "xmag", "ymag", "far", "node")
    return jobs_pb2.FrameCamera(
        **{k: c[k] for k in same},
        **{k: c[k] for k in optional if c[k] is not None},
        shutter_s=c["shutter_s"] or [],
        **flat,
    )


async def start_grpc(
    farm: FarmService,
    host: str,
    port: int,
    auth: Authenticator | None = None,
    tls: tuple[Path, Path] | None = None,
    client_ca: Path | None = None,
) -> tuple[grpc.aio.Server, int]:
    """Start the gRPC server; TLS with (certificate, key) PEM files when given, and with
    client_ca, mutual TLS: every client (worker or API caller) must present a certificate
    signed by that CA."""
    auth = auth or Authenticator.for_settings(farm.store, farm.settings)
    server = grpc.aio.server(
        options=[
            ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
            ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
            ("grpc.keepalive_time_ms", 20000),
            ("grpc.keepalive_timeout_ms", 10000),
            ("grpc.http2.max_pings_without_data", 0),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.max_frame_size", 1 << 20),
            ("grpc.http2.min_ping_interval_without_data_ms", 5000),
        ]
    )
    jobs_pb2_grpc.add_JobServiceServicer_to_server(JobServicer(farm, auth), server)
    scenes_pb2_grpc.add_SceneServiceServicer_to_server(SceneServicer(farm, auth), server)
    workers_pb2_grpc.add_WorkerServiceServicer_to_server(WorkerServicer(farm), server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = (
        jobs_pb2.DESCRIPTOR.services_by_name["JobService"].full_name,
        scenes_pb2.DESCRIPTOR.services_by_name["SceneService"].full_name,
        workers_pb2.DESCRIPTOR.services_by_name["WorkerService"].full_name,
        health.SERVICE_NAME,
        reflection.SERVICE_NAME,
    )
    reflection.enable_server_reflection(names, server)
    if tls is not None:
        credentials = grpc.ssl_server_credentials(
            [(tls[1].read_bytes(), tls[0].read_bytes())],
            root_certificates=client_ca.read_bytes() if client_ca else None,
            require_client_auth=client_ca is not None,
        )
        bound = server.add_secure_port(f"{host}:{port}", credentials)
    else:
        bound = server.add_insecure_port(f"{host}:{port}")
    if bound == 0:
        raise OSError(f"cannot listen for gRPC on {host}:{port}")
    await server.start()
    for name in names[:3] + ("",):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    return server, bound

"""The `renderfarm` command: server, up, render, submit, ls, get, watch, cancel, pause, resume,
retry, update, continue, rm, workers, token. Client commands talk to $RENDERFARM_URL (or --url)
with $RENDERFARM_TOKEN (or --token) through renderfarm.client; `token` works on the database
with the server's settings.

Every error ends the command with one line `renderfarm: MESSAGE` on stderr, never a traceback
(`--log-level debug` logs it): exit 1 when the server refused or something failed, 2 for a usage
error or a local file that is missing or unreadable, 130 on Ctrl-C (parser.main).

One module: a short function per subcommand, sharing the helpers for files, settings, the
client and the progress display above them; the arguments are in parser.py."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

from ..domain import channels, jobspec
from ..domain.frames import ALL_VARIANTS, variant_file_names
from ..domain.jobspec import SETTINGS

log = logging.getLogger("renderfarm.cli")

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
FINISHED = ("completed", "failed", "cancelled")


class CliError(Exception):
    """Ends the command with `renderfarm: message` and the exit code."""

    def __init__(self, message: str, code: int = EXIT_FAILED):
        super().__init__(message)
        self.message = message
        self.code = code


def _local_file(path: str, what: str) -> Path:
    """A file the command reads, or a usage error naming it (before anything is sent)."""
    try:
        with open(path, "rb"):
            pass
    except FileNotFoundError:
        raise CliError(f"{what} not found: {path}", EXIT_USAGE) from None
    except IsADirectoryError:
        raise CliError(f"{what} is a directory, not a file: {path}", EXIT_USAGE) from None
    except OSError as e:
        raise CliError(f"cannot read {what} {path}: {e.strerror or e}", EXIT_USAGE) from None
    return Path(path)


def _check_inputs(args: argparse.Namespace) -> None:
    """The scene and an environment map given as a file must be readable files."""
    from ..client import _is_sha256

    _local_file(args.scene, "scene file")
    environment = getattr(args, "environment", None)
    if environment and not _is_sha256(environment):
        _local_file(environment, "environment map")


def _submit(client, args: argparse.Namespace) -> dict[str, Any]:
    from ..errors import SceneError

    try:
        return client.submit(
            args.scene,
            settings=_job_settings(args),
            name=args.name or "",
            after=args.after,
            require_tags=args.require_tag,
        )
    except SceneError as e:  # packing a .gltf found what the server would refuse
        name = Path(args.scene).name
        message = e.message if name in e.message else f"{args.scene}: {e.message}"
        raise CliError(message + (f" [{e.field}]" if e.field != "scene" else "")) from None


def error_message(e: BaseException, url: str | None) -> tuple[str, int]:
    """What to tell the user about an exception that ended a command, and the exit code."""
    import httpx
    import pydantic

    from ..client import ApiError

    where = url or os.environ.get("RENDERFARM_URL") or "http://127.0.0.1:8080"
    if isinstance(e, CliError):
        return e.message, e.code
    if isinstance(e, ApiError):
        return e.message + (f" [{e.field}]" if e.field else ""), EXIT_FAILED
    if isinstance(e, httpx.UnsupportedProtocol | httpx.InvalidURL):
        return f"bad server URL {where!r}: give http://HOST:PORT or https://HOST:PORT", EXIT_USAGE
    if isinstance(e, httpx.ConnectError):
        reason = str(e)
        if "CERTIFICATE_VERIFY_FAILED" in reason:
            detail = reason.split("certificate verify failed:")[-1].split("(_ssl")[0].strip()
            return (
                f"cannot verify the TLS certificate of {where} ({detail}); set "
                "RENDERFARM_CA_FILE to the PEM certificate of the CA that signed it",
                EXIT_FAILED,
            )
        if "Connection refused" in reason:
            message = f"cannot connect to {where}: connection refused (is the server running?)"
            return message, EXIT_FAILED
        return f"cannot connect to {where}: {reason}", EXIT_FAILED
    if isinstance(e, httpx.TimeoutException):
        return (
            f"no answer from {where} in time (RENDERFARM_TIMEOUT_S sets the limit): {e}",
            EXIT_FAILED,
        )
    if isinstance(e, httpx.HTTPError):
        return f"connection to {where} failed: {e}", EXIT_FAILED
    if isinstance(e, json.JSONDecodeError):  # a 2xx answer that is not the API's JSON
        return f"{where} answered, but not as a renderfarm server does (not JSON)", EXIT_FAILED
    if isinstance(e, pydantic.ValidationError):  # a server setting (flag or environment)
        first = e.errors()[0]
        name = str(first["loc"][0]) if first.get("loc") else "settings"
        flag = "--" + name.replace("_", "-")
        return f"server setting {flag} (RENDERFARM_{name.upper()}): {first['msg']}", EXIT_USAGE
    if isinstance(e, OSError):
        return (f"{e.filename}: " if e.filename else "") + (e.strerror or str(e)), EXIT_FAILED
    return str(e) or type(e).__name__, EXIT_FAILED


def cmd_settings(args: argparse.Namespace) -> int:
    """The table of job settings (jobspec.SETTINGS), with this build's default limits."""
    if args.markdown:
        sys.stdout.write(jobspec.settings_markdown())
    elif args.json:
        print(json.dumps(jobspec.setting_docs(), indent=2))
    else:
        for doc in jobspec.setting_docs():
            default = json.dumps(doc["default"])
            print(f"{doc['name']:26s} {doc['type']:6s} {default:9s} {doc['help']}")
    return 0


def _job_settings(args: argparse.Namespace) -> dict[str, Any]:
    chosen = {s.name: getattr(args, s.name) for s in SETTINGS if getattr(args, s.name) is not None}
    if args.spp is not None:
        chosen["spp"] = args.spp
    return chosen


def _server_settings(args: argparse.Namespace, **overrides: Any):
    from ..infra.config import Settings

    chosen = {
        n: getattr(args, n) for n in Settings.model_fields if getattr(args, n, None) is not None
    }
    chosen.update({k: v for k, v in overrides.items() if v is not None})
    return Settings(**chosen)


def _client(args: argparse.Namespace, url: str | None = None):
    import ssl

    from ..client import Client

    try:
        return Client(url or args.url, token=getattr(args, "token", None))
    except ValueError as e:  # RENDERFARM_TIMEOUT_S
        raise CliError(str(e), EXIT_USAGE) from None
    except (OSError, ssl.SSLError) as e:  # RENDERFARM_CA_FILE
        ca = os.environ.get("RENDERFARM_CA_FILE", "")
        raise CliError(f"cannot read RENDERFARM_CA_FILE {ca}: {e}", EXIT_USAGE) from None


def _print_json(value: Any) -> None:
    json.dump(value, sys.stdout, indent=2)
    sys.stdout.write("\n")


def _fmt_duration(seconds: float | None) -> str:
    if seconds is None or seconds < 0:
        return "?"
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


def _progress_status(job: dict[str, Any]) -> str:
    """Everything of the progress line after the tile count."""
    p = job["progress"]
    error = "-" if p["error"] is None else f"{100 * p['error']:.2f}%"
    target = job["settings"]["noise_threshold"]
    return (
        f"{p['mean_spp']:.1f} spp  error {error} (target {100 * target:.2f}%)  "
        f"{_fmt_duration(p['elapsed_s'])} elapsed  ETA {_fmt_duration(p['eta_s'])}  {job['state']}"
    )


def _frames_text(job: dict[str, Any]) -> str:
    """ "  3/48 frames" for an animation; "" for a still."""
    p = job["progress"]
    if not job["settings"].get("frames"):
        return ""
    return f"  {p.get('frames_done', 0)}/{p.get('frames_total', 1)} frames"


def progress_line(job: dict[str, Any], width: int = 24) -> str:
    p = job["progress"]
    total = max(1, p["tiles_total"])
    filled = int(width * p["tiles_done"] / total)
    bar = "#" * filled + "-" * (width - filled)
    return (
        f"[{bar}] {p['tiles_done']}/{p['tiles_total']} tiles{_frames_text(job)}  "
        f"{_progress_status(job)}"
    )


def _watch(
    client, job_id: str, quiet: bool, as_json: bool = False, on_update=None
) -> dict[str, Any]:
    """Follow the job's Server-Sent Events until it finishes: a live progress bar (rich) when
    stderr, where it is drawn, is a terminal; one line per second otherwise; one JSON object
    per update with as_json. on_update(job) is called with every update. A job that did not
    complete is an error (exit 1)."""
    from rich.console import Console

    console = Console(stderr=True)
    job: dict[str, Any] = {}
    if as_json or quiet or not console.is_terminal:
        last_line = 0.0
        for job in client.watch(job_id):
            if on_update is not None:
                on_update(job)
            if as_json:
                sys.stdout.write(json.dumps(job) + "\n")
                sys.stdout.flush()
            elif not quiet and (job["state"] in FINISHED or time.monotonic() - last_line >= 1.0):
                last_line = time.monotonic()
                sys.stderr.write(progress_line(job) + "\n")
                sys.stderr.flush()
    else:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        columns = (
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("tiles  {task.fields[status]}"),
        )
        with Progress(*columns, console=console) as bar:
            task = bar.add_task(job_id, total=None, status="connecting")
            for job in client.watch(job_id):
                if on_update is not None:
                    on_update(job)
                p = job["progress"]
                status = _frames_text(job).strip() + "  " + _progress_status(job)
                bar.update(task, total=p["tiles_total"], completed=p["tiles_done"], status=status)
    if not job:
        raise CliError(f"the server sent nothing for job {job_id}")
    if job["state"] not in FINISHED:
        raise CliError(f"the server ended the stream of job {job_id} while it was {job['state']}")
    if job["state"] != "completed":
        raise CliError(
            f"job {job_id} {job['state']}" + (f": {job['error']}" if job["error"] else "")
        )
    return job


# --------------------------------------------------------------------------------- commands
def cmd_server(args: argparse.Namespace) -> int:
    from ..api.server import serve

    asyncio.run(serve(_server_settings(args)))
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from ..api.server import serve
    from .localfarm import spawn_workers, stop_processes

    settings = _server_settings(args)
    workers = []

    async def on_ready(http_port: int, grpc_port: int) -> None:
        address = f"127.0.0.1:{grpc_port}"
        workers.extend(spawn_workers(args.workers, address, args.threads, settings.data_dir))
        print(
            f"renderfarm is up: dashboard http://{settings.http_host}:{http_port}/  "
            f"API http://{settings.http_host}:{http_port}/docs  gRPC {address}  "
            f"workers {args.workers}  data {settings.data_dir}  (Ctrl-C stops)",
            flush=True,
        )

    try:
        asyncio.run(serve(settings, on_ready=on_ready))
    finally:
        stop_processes(workers)
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from .localfarm import LocalFarm

    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise CliError("-o must name an .exr file (a .png is written beside it)", EXIT_USAGE)
    if "#" in out.name and not args.frames and getattr(args, "variant", None) != ALL_VARIANTS:
        raise CliError("-o has a #### frame number but no --frames were given", EXIT_USAGE)
    if args.movie is not None and not args.frames:
        raise CliError("--movie needs --frames (a still has no movie)", EXIT_USAGE)
    if args.movie is not None and Path(args.movie).suffix.lower() != ".mp4":
        raise CliError("--movie must name an .mp4 file", EXIT_USAGE)
    _check_inputs(args)
    url = args.url or os.environ.get("RENDERFARM_URL")
    farm = None
    if not url:
        data_dir = Path(args.data_dir) if args.data_dir else None
        if data_dir is None:
            from ..infra.config import default_data_dir

            data_dir = default_data_dir()
        if not args.quiet:
            print(f"starting a local farm with {args.workers} workers ...", file=sys.stderr)
        farm = LocalFarm(workers=args.workers, data_dir=data_dir, threads=args.threads).start()
        url = farm.url
    try:
        with _client(args, url) as client:
            started = time.monotonic()
            job = _submit(client, args)
            if not args.quiet:
                print(f"job {job['id']} submitted to {url}", file=sys.stderr)
            every_variant = job["settings"]["variant"] == ALL_VARIANTS
            sequence = (
                FrameWriter(client, job["id"], out, every_variant)
                if job["settings"]["frames"] or every_variant
                else None
            )
            try:
                job = _watch(client, job["id"], args.quiet, on_update=sequence)
            except KeyboardInterrupt:
                try:
                    client.cancel(job["id"])
                    print(f"\ncancelled job {job['id']}", file=sys.stderr)
                except Exception as e:  # the server may be what went away
                    log.debug("cancelling job %s failed", job["id"], exc_info=True)
                    message, _ = error_message(e, url)
                    print(f"\njob {job['id']} was not cancelled: {message}", file=sys.stderr)
                return EXIT_INTERRUPTED
            p = job["progress"]
            size = f"{job['settings']['width']}x{job['settings']['height']}"
            if sequence is not None:
                sequence(job)  # the frames that finished with the job
                if every_variant:  # shoe_*.exr: one per variant, named by it
                    what, exr = f"{p['frames_total']} variants of {size}", variant_path(out, "*")
                else:
                    what, exr = f"{p['frames_total']} frames of {size}", sequence.template
            else:
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_bytes(client.image(job["id"], "exr"))
                out.with_suffix(".png").write_bytes(client.image(job["id"], "png"))
                what, exr = size, out
            print(
                f"rendered {what} in {time.monotonic() - started:.1f} s: "
                f"{p['mean_spp']:.1f} spp mean, error {100 * (p['error'] or 0):.2f}%",
                file=sys.stderr,
            )
            print(f"EXR: {exr.resolve()}")
            print(f"PNG: {exr.with_suffix('.png').resolve()}")
            if args.movie is not None and p["frames_done"]:
                movie = Path(args.movie)
                movie.parent.mkdir(parents=True, exist_ok=True)
                client.save_movie(job["id"], movie)
                print(f"movie: {movie.resolve()}")
            if args.json:
                _print_json(job)
            return 0
    finally:
        if farm is not None:
            farm.stop()


def frame_path(template: Path, frame: int) -> Path:
    """The file of one frame: the template's run of # replaced by the frame number padded to
    its length (shot_####.exr, frame 7: shot_0007.exr; frame -3: shot_-003.exr)."""
    name = template.name
    run = re.search(r"#+", name)
    if run is None:
        raise ValueError(f"{template} has no #### for the frame number")
    width = len(run.group(0))
    number = f"-{abs(frame):0{width - 1}d}" if frame < 0 else f"{frame:0{width}d}"
    return template.with_name(name[: run.start()] + number + name[run.end() :])


def variant_path(template: Path, name: str) -> Path:
    """The file of one variant's image of a job of every variant: the template's run of #
    replaced by `name` (variant_file_names), else `name` added before the suffix (shoe.exr,
    variant Red: shoe_Red.exr)."""
    if "#" in template.name:
        return template.with_name(re.sub(r"#+", name, template.name, count=1))
    return template.with_name(f"{template.stem}_{name}{template.suffix}")


class FrameWriter:
    """Writes each frame of an animation job (EXR and PNG, from the -o template) as soon as it
    is done, so a long sequence is on disk frame by frame (called with every job update). For
    a job of every variant (settings.variant "all") each variant's image is named by the
    variant (variant_path)."""

    def __init__(self, client, job_id: str, template: Path, variants: bool = False):
        self.variants = variants
        if not variants and "#" not in template.name:  # shot.exr -> shot_####.exr
            template = template.with_name(f"{template.stem}_####{template.suffix}")
        self.client, self.job_id, self.template = client, job_id, template
        self.written: set[int] = set()
        self.done_seen = 0
        self.names: dict[int, str] = {}  # a variant's index -> its part of the file name

    def __call__(self, job: dict[str, Any]) -> None:
        done = job["progress"].get("frames_done", 0)
        if done <= self.done_seen and job["state"] not in FINISHED:
            return
        self.done_seen = done
        frames = self.client.frames(self.job_id)
        if self.variants and not self.names:
            names = variant_file_names([f.get("variant") or "" for f in frames])
            self.names = {f["frame"]: n for f, n in zip(frames, names, strict=True)}
        for f in frames:
            if f["state"] != "done" or f["frame"] in self.written:
                continue
            if self.variants:
                path = variant_path(self.template, self.names[f["frame"]])
            else:
                path = frame_path(self.template, f["frame"])
            path.parent.mkdir(parents=True, exist_ok=True)
            self.client.save_image(self.job_id, path, "exr", frame=f["frame"])
            self.client.save_image(self.job_id, path.with_suffix(".png"), "png", frame=f["frame"])
            self.written.add(f["frame"])


def cmd_submit(args: argparse.Namespace) -> int:
    _check_inputs(args)
    with _client(args) as client:
        job = _submit(client, args)
        if args.json:
            _print_json(job)
        else:
            print(job["id"], flush=True)
        if args.wait:
            _watch(client, job["id"], args.quiet)
    return 0


def cmd_ls(args: argparse.Namespace) -> int:
    with _client(args) as client:
        page = client.list(state=args.state or "", page_size=args.limit)
        if args.json:
            _print_json(page)
            return 0
        print(f"{'ID':12}  {'STATE':9}  {'TILES':>9}  {'SPP':>7}  {'ERROR':>7}  NAME")
        for job in page["jobs"]:
            p = job["progress"]
            err = "-" if p["error"] is None else f"{100 * p['error']:.2f}%"
            tiles = f"{p['tiles_done']}/{p['tiles_total']}"
            print(
                f"{job['id']:12}  {job['state']:9}  {tiles:>9}  {p['mean_spp']:7.1f}  "
                f"{err:>7}  {job['name']}"
            )
    return 0


# The EXR channels of each layer (the channel table's), for `get -o out.exr --layer NAME`.
EXR_LAYER_CHANNELS = {name: layer.exr for name, layer in channels.layers().items()}


def _image_format(output: str) -> str:
    fmt = Path(output).suffix.lower().lstrip(".")
    if fmt not in ("exr", "png"):
        raise CliError(
            f"-o {output}: the format comes from the extension, .exr or .png", EXIT_USAGE
        )
    return fmt


def _save_image(
    client, job_id: str, output: str, layer: str | None, group: str | None = None
) -> None:
    """The job's image into `output`: a PNG of one layer (rgb by default), the whole EXR, or
    an EXR of one layer's channels (taken from the whole EXR, header attributes kept). group:
    of the light_group layer, one light group (None: the PNG the first, the EXR every one)."""
    fmt = _image_format(output)
    if layer is not None and layer not in EXR_LAYER_CHANNELS:
        raise CliError(
            f"--layer {layer}: unknown layer; one of {', '.join(EXR_LAYER_CHANNELS)}", EXIT_USAGE
        )
    if group is not None and layer != channels.LIGHT_GROUP_LAYER:
        raise CliError(
            f"--group picks a light group of --layer {channels.LIGHT_GROUP_LAYER}", EXIT_USAGE
        )
    out = Path(output)
    if not out.parent.is_dir():
        raise CliError(f"-o {output}: no such directory {out.parent}", EXIT_USAGE)
    if fmt == "png" or layer is None:
        partial = out.with_name(f".{out.name}.part")
        try:
            client.save_image(job_id, partial, fmt, layer or "rgb", group=group or "")
            partial.replace(out)  # a failed download leaves no half file under the name
        finally:
            partial.unlink(missing_ok=True)
        return
    import tempfile

    import OpenImageIO as oiio

    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".renderfarm-") as scratch:
        whole = Path(scratch) / "whole.exr"
        client.save_image(job_id, whole, "exr")
        source = oiio.ImageBuf(str(whole))
        wanted = EXR_LAYER_CHANNELS[layer]
        present = source.spec().channelnames
        if layer == channels.LIGHT_GROUP_LAYER:  # the job's groups: every one, or the one named
            start = layer + "_"  # light_group_<group>.R
            # The groups in their layers' order: the job's settings in the header (OpenEXR
            # keeps channels sorted by name).
            recorded = json.loads(source.spec().getattribute("renderfarm:settings") or "{}")
            groups = list(json.loads(recorded.get("light_groups") or "{}"))
            if group is not None and groups and group not in groups:
                raise CliError(
                    f"job {job_id} has no light group {group!r}; its groups: {', '.join(groups)}"
                )
            if groups:
                prefix = f"{start}{group}." if group else start
                wanted = tuple(c for c in present if c.startswith(prefix))
        if not all(c in present for c in wanted):
            row = channels.layer_channel(layer)
            flag = f"--aovs naming {row.aov}" if row.aov else f"--{row.setting}"
            raise CliError(f"job {job_id} has no {layer} layer (it was submitted without {flag})")
        part = oiio.ImageBufAlgo.channels(source, tuple(wanted))
        target = Path(scratch) / "layer.exr"
        if part.has_error or not part.write(str(target)):
            raise CliError(f"cannot write {output}: {part.geterror() or oiio.geterror()}")
        target.replace(out)


def cmd_get(args: argparse.Namespace) -> int:
    with _client(args) as client:
        if args.movie is not None:
            if args.output is not None:
                raise CliError("-o and --movie download one thing each: give one", EXIT_USAGE)
            client.save_movie(args.job_id, args.movie)
            if args.json:
                _print_json({"id": args.job_id, "movie": str(Path(args.movie).resolve())})
            else:
                print(Path(args.movie).resolve())
            return 0
        if args.output is not None:
            _save_image(client, args.job_id, args.output, args.layer, args.group)
            if not args.json:
                print(Path(args.output).resolve())
            else:
                _print_json({"id": args.job_id, "output": str(Path(args.output).resolve())})
            return 0
        if args.layer is not None or args.group is not None:
            raise CliError("--layer and --group need -o FILE (the image to write)", EXIT_USAGE)
        job = client.get(args.job_id)
        if args.json:
            _print_json(job)
        else:
            print(f"{job['id']}  {job['name']}  {job['state']}")
            print(progress_line(job))
            if job["error"]:
                print(f"error: {job['error']}")
    return 0


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.cancel(args.job_id)
        if args.json:
            _print_json(job)
        else:
            print(f"{job['id']} {job['state']}")
    return 0


def _control(args: argparse.Namespace, act) -> int:
    """A job-control command: do it, print the job's id and new state (or the job as JSON)."""
    with _client(args) as client:
        job = act(client)
        if args.json:
            _print_json(job)
        else:
            print(f"{job['id']} {job['state']}")
    return 0


def cmd_pause(args: argparse.Namespace) -> int:
    return _control(args, lambda c: c.pause(args.job_id))


def cmd_resume(args: argparse.Namespace) -> int:
    return _control(args, lambda c: c.resume(args.job_id))


def cmd_retry(args: argparse.Namespace) -> int:
    return _control(args, lambda c: c.retry(args.job_id))


def cmd_update(args: argparse.Namespace) -> int:
    if args.priority is None and args.name is None:
        raise CliError("update needs --priority or --name", EXIT_USAGE)
    return _control(args, lambda c: c.update(args.job_id, priority=args.priority, name=args.name))


def cmd_continue(args: argparse.Namespace) -> int:
    if args.max_spp is None and args.noise_threshold is None:
        raise CliError("continue needs --max-spp or --noise-threshold", EXIT_USAGE)
    return _control(
        args,
        lambda c: c.continue_job(
            args.job_id, max_spp=args.max_spp, noise_threshold=args.noise_threshold
        ),
    )


def cmd_watch(args: argparse.Namespace) -> int:
    with _client(args) as client:
        _watch(client, args.job_id, quiet=False, as_json=args.json)
    return 0


def cmd_rm(args: argparse.Namespace) -> int:
    with _client(args) as client:
        for job_id in args.job_ids:
            client.delete(job_id)
            if args.json:
                _print_json({"id": job_id, "deleted": True})
            else:
                print(f"{job_id} deleted")
    return 0


def cmd_token(args: argparse.Namespace) -> int:
    import psycopg
    from psycopg_pool import PoolTimeout

    settings = _server_settings(args)
    # The pool's retries would log a warning each; the one-line error below says it all.
    logging.getLogger("psycopg.pool").setLevel(logging.ERROR)
    try:
        return _token_command(args, settings)
    except (psycopg.Error, PoolTimeout) as e:
        where = "RENDERFARM_DATABASE_URL" if settings.database_url else str(settings.data_dir)
        raise CliError(f"cannot use the database ({where}): {e}") from None


def _token_command(args: argparse.Namespace, settings) -> int:
    from . import tokens

    if args.token_command == "create":
        try:
            info, token = tokens.create(settings, args.name, args.admin)
        except ValueError as e:
            raise CliError(str(e)) from None
        if args.json:
            _print_json({**info, "token": token})
        else:
            role = "admin " if info["admin"] else ""
            print(f"created {role}token {info['id']} ({info['name']}); it is shown only once:")
            print(token)
        return 0
    if args.token_command == "ls":
        listed = tokens.list_all(settings)
        if args.json:
            _print_json(listed)
            return 0
        print(f"{'ID':8}  {'NAME':24}  {'ADMIN':5}  {'CREATED':19}  REVOKED")
        for t in listed:
            created = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t["created_unix_s"]))
            revoked = (
                time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t["revoked_unix_s"]))
                if t["revoked_unix_s"]
                else "-"
            )
            print(f"{t['id']:8}  {t['name']:24}  {str(t['admin']).lower():5}  {created}  {revoked}")
        return 0
    revoked = tokens.revoke(settings, args.token_id)
    if revoked is None:
        raise CliError(f"no live token with id {args.token_id}")
    if args.json:
        _print_json(revoked)
    else:
        print(f"revoked token {revoked['id']} ({revoked['name']})")
    return 0


def cmd_workers(args: argparse.Namespace) -> int:
    if args.action is not None:
        if not args.worker_id:
            print(f"error: renderfarm workers {args.action} needs a worker ID", file=sys.stderr)
            return 2
        with _client(args) as client:
            w = getattr(client, f"{args.action}_worker")(args.worker_id)
        if args.json:
            _print_json(w)
        else:
            print(f"{w['id']} {w['state']}")
        return 0
    with _client(args) as client:
        workers = client.workers()
        if args.json:
            _print_json(workers)
            return 0
        print(
            f"{'ID':32}  {'STATE':8}  {'CORES':>5}  {'TASKS':>5}  {'DONE':>6}  {'FAILED':>6}  "
            f"{'SAMPLES/S':>12}  {'MRAYS/S':>8}"
        )
        for w in workers:
            print(
                f"{w['id']:32}  {w['state']:8}  {w['cores']:5}  {w['tasks_in_flight']:5}  "
                f"{w['tasks_done']:6}  {w['tasks_failed']:6}  "
                f"{w['samples_per_s']:12,.0f}  {w['rays_per_s'] / 1e6:8.2f}"
            )
            for error in w["recent_errors"]:
                print(f"    error: {error}")
    return 0


def cmd_replicas(args: argparse.Namespace) -> int:
    """The servers of the farm (several over one database, or this one alone)."""
    with _client(args) as client:
        replicas = client.replicas()
    if args.json:
        _print_json(replicas)
        return 0
    now = time.time()
    print(f"{'ID':32}  {'LIVE':4}  {'JOBS':>4}  {'MERGED':>9}  {'BATCHES/S':>9}  {'SEEN':>7}")
    for r in replicas:
        seen = now - r["heartbeat_unix_s"] if r["heartbeat_unix_s"] is not None else None
        rate = r["merge_rate"]
        print(
            f"{r['id']:32}  {'yes' if r['live'] else 'no':4}  {r['jobs_owned']:4}  "
            f"{r['batches_merged']:9}  {'-' if rate is None else f'{rate:,.1f}':>9}  "
            f"{'-' if seen is None else f'{seen:,.0f} s ago':>7}"
        )
    return 0

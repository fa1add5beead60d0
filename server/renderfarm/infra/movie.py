"""Preview movies: a sequence of PNG frames encoded as an H.264 MP4 by ffmpeg (Debian's
package, which is built with libx264).

The encoder is a child process with a wall-clock limit; it reads the frames from a directory
and writes the movie into a file beside the final one, which is renamed into place only when
ffmpeg succeeded, so a half-written movie is never served.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
from pathlib import Path

# Every frame is a keyframe candidate at a constant quality; veryfast keeps a preview of a few
# hundred frames to seconds. yuv420p is what browsers and players decode; it needs even sides.
X264_ARGS = ("-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p")
EVEN_SIDES = "scale=trunc(iw/2)*2:trunc(ih/2)*2"


class MovieError(RuntimeError):
    """The server could not make the movie: ffmpeg failed or ran out of time (REST 503)."""


class EncoderMissing(MovieError):
    """ffmpeg is not installed where the server runs (REST 503)."""


def find_ffmpeg() -> str:
    """The ffmpeg on PATH, or EncoderMissing saying how to install it."""
    path = shutil.which("ffmpeg")
    if path is None:
        raise EncoderMissing(
            "the server cannot make preview movies: ffmpeg is not installed where it runs "
            "(Debian: apt install ffmpeg)"
        )
    return path


async def encode_mp4(frames_dir: Path, pattern: str, fps: float, out: Path, timeout_s: float):
    """Encode frames_dir/pattern (a printf pattern numbered from 0, e.g. "f%05d.png") at fps
    into out (an MP4 with its index at the front, so browsers play it while it downloads).
    MovieError with ffmpeg's last words when it fails, or saying so when it runs past
    timeout_s."""
    ffmpeg = find_ffmpeg()
    partial = out.with_name(out.name + ".partial")
    args = [
        ffmpeg, "-nostdin", "-hide_banner", "-loglevel", "error", "-y",
        "-framerate", f"{fps:g}", "-start_number", "0", "-i", str(frames_dir / pattern),
        *X264_ARGS, "-vf", EVEN_SIDES, "-movflags", "+faststart", "-f", "mp4", str(partial),
    ]  # fmt: skip
    proc = await asyncio.create_subprocess_exec(
        *args,
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        _, err = await asyncio.wait_for(proc.communicate(), timeout=timeout_s)
    except BaseException as e:  # the time limit, or the request went away
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        await proc.wait()
        with contextlib.suppress(OSError):
            partial.unlink()
        if isinstance(e, TimeoutError):
            raise MovieError(f"ffmpeg took more than {timeout_s:g} s to encode the movie") from None
        raise
    if proc.returncode != 0:
        with contextlib.suppress(OSError):
            partial.unlink()
        words = err.decode(errors="replace").strip()[-1000:]
        raise MovieError(f"ffmpeg failed (status {proc.returncode}): {words}")
    os.replace(partial, out)

"""A job's preview movie: its finished frames, in frame order, encoded as an H.264 MP4 at the
job's fps (infra/movie.py).

A movie is made when it is first asked for and kept in DATA_DIR/movies under a name that
depends on which frames are finished and how many samples they hold, so a request for the
same frames (a browser's range requests while it plays) is served from the file, a frame
finishing later makes the next request encode a new movie, and a continued job's movie is made
again from its deeper frames. One movie is encoded at a time.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import shutil
import tempfile
from pathlib import Path

from ..errors import Conflict, NotFound, SettingsError
from ..infra import movie
from .auth import Caller

MAX_MOVIE_SIZE = 4096  # largest side a movie may ask for (H.264 level 5.1 tops out near it)
DEFAULT_MOVIE_SIZE = 1920
ENCODE_TIMEOUT_S = 1800.0


class JobMovies:
    """Part of FarmService (jobs.py), whose __init__ sets the attributes used here."""

    def _movie_dir(self) -> Path:
        return self.settings.data_dir / "movies"

    async def movie_file(
        self, job_id: str, caller: Caller, max_size: int = DEFAULT_MOVIE_SIZE
    ) -> Path:
        """The preview movie of the job's finished frames (a file under DATA_DIR/movies,
        made now if it is not there). NotFound for a still; Conflict while no frame is
        finished; movie.MovieError without ffmpeg or when it fails."""
        if not 16 <= max_size <= MAX_MOVIE_SIZE:
            raise SettingsError("max_size", f"max_size must be in 16..{MAX_MOVIE_SIZE}")
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        if not view.settings.frames:
            raise NotFound(f"job {job_id} renders a still: it has no preview movie")
        frames = await self.frames(job_id, caller)
        done = [f for f in frames if f.state == "done"]
        if not done:
            raise Conflict(f"no frame of job {job_id} has finished yet: the movie has none to show")
        movie.find_ffmpeg()  # before any work: say at once that the server cannot do it
        fps = float(view.settings.fps)
        key = json.dumps(
            [[f.frame, f.mean_spp] for f in done] + [fps, max_size, view.scene_sha256]
        ).encode()
        path = self._movie_dir() / f"{job_id}-{hashlib.sha256(key).hexdigest()[:16]}.mp4"
        if path.exists():
            return path
        async with self._movie_turn:
            if path.exists():  # made while this request waited for its turn
                return path
            path.parent.mkdir(parents=True, exist_ok=True)
            work = Path(tempfile.mkdtemp(prefix=f"movie-{job_id}-", dir=path.parent))
            try:
                for i, f in enumerate(done):
                    png = await self.image_file(
                        job_id, "png", "rgb", caller, max_size=max_size, frame=f.frame
                    )
                    with png, open(work / f"f{i:06d}.png", "wb") as out:
                        await asyncio.to_thread(shutil.copyfileobj, png, out)
                await movie.encode_mp4(work, "f%06d.png", fps, path, ENCODE_TIMEOUT_S)
            finally:
                await asyncio.to_thread(shutil.rmtree, work, True)
            self._forget_movies(job_id, keep=path)
        return path

    def _forget_movies(self, job_id: str, keep: Path | None = None) -> None:
        """Remove the job's stored movies (but keep)."""
        directory = self._movie_dir()
        if not directory.is_dir():
            return
        for old in directory.glob(f"{job_id}-*.mp4"):
            if old != keep:
                with contextlib.suppress(OSError):
                    old.unlink()

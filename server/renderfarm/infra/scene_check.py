"""Scene acceptance: an uploaded scene is accepted only if the workers' own loader accepts it.

The server runs `renderfarm-worker inspect --json` (the loader every worker uses, with the
server's limits) on each new scene before it stores it, in a child process under CPU-time and
address-space limits, so that a scene the server accepts can neither be refused by the workers
nor hang or exhaust them; and a hostile scene costs the server one bounded child process. There
is no second validator here that could drift from the loader: domain/scenes only reads the upload's
container (GLB or JSON, sizes, self-containment) and this module asks the loader.

The loader refuses, naming the glTF path of the offending part (`scene.nodes[3].children`):
node graphs that are not disjoint trees (a node with two parents, a cycle), hierarchies deeper
than `max_scene_depth` or with more than `max_scene_nodes` nodes, mesh uses adding up to more
than `max_scene_triangles` triangles, images over `max_texture_pixels` in all, an estimated
memory over `max_scene_memory_mb`, an `extensionsRequired` entry it does not implement,
out-of-range indices and accessors, degenerate cameras and every other malformed part.

The same child process, under the same limits, says which camera a job's images are rendered
through (`renderfarm-worker camera`, SceneChecker.cameras): the workers' own loader and poses,
so the camera data the server publishes (domain/camera.py) is the renderer's.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import signal
import tempfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import SceneError

log = logging.getLogger(__name__)

# Address space the inspecting process needs beyond the scene itself: the worker binary maps
# about 0.6 GB of shared libraries and thread stacks before it reads a byte.
BASE_ADDRESS_SPACE = 1 << 30


@dataclass(frozen=True)
class SceneLimits:
    """What a scene may cost a worker (server settings RENDERFARM_MAX_SCENE_*)."""

    max_nodes: int
    max_depth: int
    max_triangles: int
    max_texture_pixels: int
    max_memory_mb: int
    cpu_seconds: float

    def flags(self) -> list[str]:
        return [
            "--max-nodes", str(self.max_nodes),
            "--max-depth", str(self.max_depth),
            "--max-triangles", str(self.max_triangles),
            "--max-texture-pixels", str(self.max_texture_pixels),
            "--max-memory-mb", str(self.max_memory_mb),
        ]  # fmt: skip


class SceneChecker:
    """Runs the workers' loader on uploaded scenes; remembers the verdicts by content hash."""

    def __init__(self, binary: str, limits: SceneLimits, tmp_dir: Path, concurrency: int = 1):
        if not (os.path.isfile(binary) and os.access(binary, os.X_OK)):
            raise RuntimeError(
                f"the scene inspector {binary} is not an executable file "
                "(RENDERFARM_SCENE_INSPECTOR: a renderfarm-worker binary)"
            )
        self.binary = binary
        self.limits = limits
        prlimit = shutil.which("prlimit")
        if prlimit is None:
            raise RuntimeError("prlimit (util-linux) is needed to check uploaded scenes")
        self.prlimit = prlimit
        self.tmp_dir = Path(tmp_dir)
        # One inspection at a time by default: each may use up to max_scene_memory_mb.
        self._slots = asyncio.Semaphore(max(1, concurrency))
        self._accepted: OrderedDict[str, dict[str, Any]] = OrderedDict()

    async def check(self, data: bytes, filename: str, sha256: str) -> dict[str, Any]:
        """The loader's description of the scene (triangles, nodes, memory, warnings), or
        SceneError with the loader's message and the glTF path as the field."""
        known = self._accepted.get(sha256)
        if known is not None:
            self._accepted.move_to_end(sha256)
            return known
        async with self._slots:
            info = await self._inspect(data, filename)
        self._accepted[sha256] = info
        while len(self._accepted) > 4096:
            self._accepted.popitem(last=False)
        return info

    async def _inspect(self, data: bytes, filename: str) -> dict[str, Any]:
        name = filename or "scene"
        inspect = ["inspect", "--json", "--name", name, *self.limits.flags()]
        code, result, err = await self._run(data, inspect, name)
        if code == 0 and result and result.get("ok"):
            return result
        raise self._refusal(code, result, err, name)

    async def cameras(
        self,
        data: bytes,
        filename: str,
        times: list[float] | None,
        animation: str = "",
        shutter: str = "",
        fps: float = 24.0,
    ) -> list[dict[str, Any]]:
        """The camera each image is rendered through (`renderfarm-worker camera`): the still's
        (times None: the scene as stored) or the camera at each of `times` (glTF seconds),
        posed by the animations `animation` selects (settings.animation); `shutter` and `fps`
        (settings) pose a scene without a camera as the renderer does. One dict per image:
        position, right, up, forward, projection, yfov, xmag, ymag, znear, zfar (None:
        infinite), node (None: the camera that frames a scene without one). SceneError when
        the loader refuses the scene or the limits stop it."""
        name = filename or "scene"
        args = ["camera", "--json"]
        if times is not None:
            args += ["--times", ",".join(repr(float(t)) for t in times)]
            if animation:
                args += ["--animations", animation]
            if shutter:
                args += ["--shutter", shutter, "--fps", repr(float(fps))]
        async with self._slots:  # each time may cost a load: the CPU limit is per time
            code, result, err = await self._run(data, args, name, len(times or [None]))
        if code == 0 and result and result.get("ok"):
            return list(result["cameras"])
        raise self._refusal(code, result, err, name)

    async def _run(
        self, data: bytes, command: list[str], name: str, loads: int = 1
    ) -> tuple[int | None, dict[str, Any] | None, bytes]:
        """The worker binary's `command` on `data` (a temporary copy, removed after) under the
        limits (`loads` times the CPU time of one): its exit status, the JSON object its
        output ends with, and its stderr."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        suffix = ".glb" if data[:4] == b"glTF" else ".gltf"
        fd, path = tempfile.mkstemp(prefix="inspect-", suffix=suffix, dir=self.tmp_dir)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            return await self._run_file(path, command, name, len(data), loads)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(path)

    async def _run_file(
        self, path: str, command: list[str], name: str, size: int, loads: int
    ) -> tuple[int | None, dict[str, Any] | None, bytes]:
        limits = self.limits
        cpu = max(1, int(loads * limits.cpu_seconds + 0.999))
        address_space = BASE_ADDRESS_SPACE + 2 * size + int(1.5 * limits.max_memory_mb * 10**6)

        # prlimit (util-linux) sets the limits between fork and exec; a preexec_fn would run
        # Python in a child forked from a process with gRPC's threads, which is not safe.
        args = [
            self.prlimit, f"--cpu={cpu}:{cpu + 1}", f"--as={address_space}", "--core=0", "--",
            self.binary, *command, path,
        ]  # fmt: skip
        proc = await asyncio.create_subprocess_exec(
            *args,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        # The CPU limit ends a busy loader; the wall-clock one a stalled one (twice the CPU
        # time plus the process's start, which is slow on a loaded machine).
        try:
            out, err = await asyncio.wait_for(proc.communicate(), timeout=2 * cpu + 30)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
            raise SceneError(self._too_costly(name, "time")) from None
        return proc.returncode, parse_last_json_line(out), err

    def _refusal(
        self, code: int | None, result: dict[str, Any] | None, err: bytes, name: str
    ) -> SceneError:
        """Why the loader did not answer ok: its own verdict, or the limits at work."""
        if code == 1 and result and not result.get("ok"):
            path_in_gltf = str(result.get("path") or "")
            field = f"scene.{path_in_gltf}" if path_in_gltf else "scene"
            return SceneError(str(result.get("error") or f"{name}: refused"), field)
        if code in (-signal.SIGXCPU, -signal.SIGKILL):
            return SceneError(self._too_costly(name, "time"))
        # Anything else is the limits at work (an allocation refused under RLIMIT_AS ends in
        # std::bad_alloc or an abort inside a library), or a loader crash: either way the
        # workers could not load this scene.
        log.warning(
            "renderfarm-worker on %s ended with status %s: %s",
            name,
            code,
            err.decode(errors="replace")[-2000:],
        )
        return SceneError(self._too_costly(name, "memory"))

    def _too_costly(self, name: str, what: str) -> str:
        if what == "time":
            return (
                f"{name}: loading the scene took more than the server's limit of "
                f"{self.limits.cpu_seconds:g} s of CPU time (RENDERFARM_SCENE_INSPECT_CPU_S)"
            )
        return (
            f"{name}: the scene cannot be loaded within the server's limits of "
            f"{self.limits.max_memory_mb} MB of memory (RENDERFARM_MAX_SCENE_MEMORY_MB) and "
            f"{self.limits.cpu_seconds:g} s of CPU time (RENDERFARM_SCENE_INSPECT_CPU_S)"
        )


def parse_last_json_line(out: bytes) -> dict[str, Any] | None:
    """A child process's answer: the JSON object on the last line of its output, or None."""
    try:
        value = json.loads(out.decode(errors="replace").strip().splitlines()[-1])
    except (ValueError, IndexError):
        return None
    return value if isinstance(value, dict) else None

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
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        suffix = ".glb" if data[:4] == b"glTF" else ".gltf"
        fd, path = tempfile.mkstemp(prefix="inspect-", suffix=suffix, dir=self.tmp_dir)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            return await self._run(path, filename or "scene", len(data))
        finally:
            with contextlib.suppress(OSError):
                os.unlink(path)

    async def _run(self, path: str, name: str, size: int) -> dict[str, Any]:
        limits = self.limits
        cpu = max(1, int(limits.cpu_seconds + 0.999))
        address_space = BASE_ADDRESS_SPACE + 2 * size + int(1.5 * limits.max_memory_mb * 10**6)

        # prlimit (util-linux) sets the limits between fork and exec; a preexec_fn would run
        # Python in a child forked from a process with gRPC's threads, which is not safe.
        args = [
            self.prlimit, f"--cpu={cpu}:{cpu + 1}", f"--as={address_space}", "--core=0", "--",
            self.binary, "inspect", "--json", "--name", name, *limits.flags(), path,
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
        result = parse_last_json_line(out)
        if proc.returncode == 0 and result and result.get("ok"):
            return result
        if proc.returncode == 1 and result and not result.get("ok"):
            path_in_gltf = str(result.get("path") or "")
            field = f"scene.{path_in_gltf}" if path_in_gltf else "scene"
            raise SceneError(str(result.get("error") or f"{name}: refused"), field)
        if proc.returncode in (-signal.SIGXCPU, -signal.SIGKILL):
            raise SceneError(self._too_costly(name, "time"))
        # Anything else is the limits at work (an allocation refused under RLIMIT_AS ends in
        # std::bad_alloc or an abort inside a library), or a loader crash: either way the
        # workers could not load this scene.
        log.warning(
            "scene inspection of %s ended with status %s: %s",
            name,
            proc.returncode,
            err.decode(errors="replace")[-2000:],
        )
        raise SceneError(self._too_costly(name, "memory"))

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

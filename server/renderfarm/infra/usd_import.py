"""USD uploads converted to the farm's glTF in a child process under limits.

The server never opens a USD stage itself: a stage can name any file, and composing one can
take any time and memory. `UsdImporter.convert` lays the upload's files out in a fresh private
directory (domain/scenes/usd_upload.py), then runs this module as a child process
(`python -m renderfarm.infra.usd_import DIR ROOT OUT`) through prlimit, with CPU-time,
address-space, file-size and open-file limits, its working directory and HOME that directory,
and an environment without any PXR_* variable (so no plug-in or search path of the server's
applies). The child checks every asset path of every layer before the stage is composed
(domain/scenes/usd_assets.py: no layer outside the directory is opened, no texture outside it
read), composes, refuses the stage if it used any layer outside the directory nonetheless (after
composition and after the conversion), converts (domain/scenes/usd_convert.py), writes the GLB
and prints one JSON line. Before it opens the upload, the child confines itself with Landlock
where the kernel has it (infra/landlock.py: read only the upload, Python, its packages and the
system's libraries; write only its output folder, work/out), so that what the checks might miss
the kernel denies; without Landlock it converts anyway and the server logs a notice once. The
GLB then goes through the ordinary acceptance (the workers' loader), like any other upload.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import os
import posixpath
import shutil
import signal
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from ..domain.scenes.usd_upload import usd_files, usd_kind
from ..errors import SceneError
from .landlock import confine
from .scene_check import parse_last_json_line

log = logging.getLogger(__name__)

# What the child needs before it reads a byte: Python, numpy, OpenImageIO and usd-core's
# libraries and plug-in registry map about 1.5 GB of address space.
BASE_ADDRESS_SPACE = 3 << 30


@dataclass(frozen=True)
class UsdImport:
    """A converted USD upload: the GLB to accept and store, and what the user should know."""

    glb: bytes
    filename: str  # the GLB's name: the upload's stem + ".glb"
    source_sha256: str  # the USD upload's own hash (the bytes as uploaded)
    source_filename: str
    warnings: list[str] = field(default_factory=list)
    camera: dict[str, float] = field(default_factory=dict)  # aperture_radius, focus_distance
    # A dome light: the environment map's bytes and name, and its environment_intensity and
    # environment_rotation_deg.
    environment_data: bytes | None = None
    environment_filename: str = ""
    environment: dict[str, float] = field(default_factory=dict)
    # How the child's file-system access was confined: "enforced (Landlock ABI n)" or
    # "unavailable: why" (then its own checks alone kept it to the upload).
    confinement: str = ""


class UsdImporter:
    """Converts USD uploads one (by default) at a time in a limited child process."""

    def __init__(
        self,
        tmp_dir: Path,
        *,
        cpu_seconds: float = 60.0,
        memory_mb: int = 2048,
        max_output_bytes: int = 256 * 2**20,
        concurrency: int = 1,
        python: str = sys.executable,
    ):
        prlimit = shutil.which("prlimit")
        if prlimit is None:
            raise RuntimeError("prlimit (util-linux) is needed to convert USD uploads")
        self.prlimit = prlimit
        self.tmp_dir = Path(tmp_dir)
        self.cpu_seconds = cpu_seconds
        self.memory_mb = memory_mb
        self.max_output_bytes = max_output_bytes
        self.python = python
        self._slots = asyncio.Semaphore(max(1, concurrency))
        self._told = False  # the notice that Landlock is unavailable, logged once

    @staticmethod
    def is_usd(data: bytes | None, filename: str = "") -> bool:
        return usd_kind(data, filename) is not None

    async def convert(self, data: bytes, filename: str) -> UsdImport:
        """The upload converted (SceneError naming the prim and attribute, or the limits).
        Unpacking, writing and hashing run in a thread: the event loop serves meanwhile."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix="usd-", dir=self.tmp_dir))
        try:
            root_layer, source_sha256 = await asyncio.to_thread(
                self._lay_out, data, filename, work / "upload"
            )
            out = work / "out" / "scene.glb"  # the only folder the child may write in
            out.parent.mkdir()
            async with self._slots:
                result = await self._run(
                    work / "upload", root_layer, out, out.parent, filename or root_layer
                )
            env = dict(result.get("environment") or {})
            glb, env_data = await asyncio.to_thread(
                lambda: (
                    out.read_bytes(),
                    (out.parent / "environment").read_bytes() if env else None,
                )
            )
            confinement = str(result.get("confinement") or "")
            if not confinement.startswith("enforced") and not self._told:
                self._told = True
                log.warning("USD conversions are not confined by the kernel (%s): the "
                            "child's own checks keep them to the upload", confinement)  # fmt: skip
        finally:
            await asyncio.to_thread(shutil.rmtree, work, True)
        stem = posixpath.splitext(posixpath.basename((filename or root_layer).replace("\\", "/")))
        return UsdImport(
            glb=glb,
            filename=(stem[0] or "scene") + ".glb",
            source_sha256=source_sha256,
            source_filename=filename or root_layer,
            warnings=[str(w) for w in result.get("warnings", [])],
            camera={k: float(v) for k, v in dict(result.get("camera") or {}).items()},
            environment_data=env_data,
            environment_filename=str(env.get("filename") or ""),
            environment={
                "environment_intensity": float(env.get("intensity", 1.0)),
                "environment_rotation_deg": float(env.get("rotation_deg", 0.0)),
            }
            if env
            else {},
            confinement=confinement,
        )

    def _lay_out(self, data: bytes, filename: str, upload: Path) -> tuple[str, str]:
        """Write the upload's files under `upload`; (the root layer's path, the sha256)."""
        kind = usd_kind(data, filename)
        if kind is None:
            raise SceneError(f"{filename or 'scene'} is not a USD upload")
        files, root_layer = usd_files(data, filename, kind, self.max_output_bytes)
        for rel, content in files.items():
            target = upload / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(content)
        return root_layer, hashlib.sha256(data).hexdigest()

    async def _run(self, upload: Path, root_layer: str, out: Path, work: Path, name: str):
        cpu = max(1, int(self.cpu_seconds + 0.999))
        address_space = BASE_ADDRESS_SPACE + int(self.memory_mb * 2**20)
        fsize = self.max_output_bytes + (1 << 20)
        env = {
            k: os.environ[k] for k in ("PATH", "PYTHONPATH", "LANG", "LC_ALL") if k in os.environ
        }
        env.update(HOME=str(work), TMPDIR=str(work), PYTHONDONTWRITEBYTECODE="1")
        args = [
            self.prlimit, f"--cpu={cpu}:{cpu + 1}", f"--as={address_space}", f"--fsize={fsize}",
            "--nofile=256", "--core=0", "--",
            self.python, "-P", "-s", "-m", "renderfarm.infra.usd_import",
            str(upload), root_layer, str(out),
        ]  # fmt: skip
        proc = await asyncio.create_subprocess_exec(
            *args,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            cwd=str(work),
            env=env,
        )
        try:
            stdout, stderr = await asyncio.wait_for(proc.communicate(), timeout=2 * cpu + 30)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
            raise SceneError(self._too_costly(name)) from None
        result = parse_last_json_line(stdout)
        if proc.returncode == 0 and result and result.get("ok"):
            return result
        if result and not result.get("ok") and result.get("error"):
            raise SceneError(str(result["error"]), str(result.get("field") or "scene"))
        log.warning(
            "USD conversion of %s ended with status %s: %s",
            name,
            proc.returncode,
            stderr.decode(errors="replace")[-2000:],
        )
        if proc.returncode in (-signal.SIGXCPU, -signal.SIGKILL, -signal.SIGXFSZ):
            raise SceneError(self._too_costly(name))
        raise SceneError(self._too_costly(name))

    def _too_costly(self, name: str) -> str:
        return (
            f"{name}: the USD stage cannot be converted within the server's limits of "
            f"{self.cpu_seconds:g} s of CPU time, {self.memory_mb} MB of memory and "
            f"{self.max_output_bytes} bytes of glTF"
        )


def readable_paths(upload: Path) -> list[str]:
    """What the child may read once confined: the upload, Python and its packages (every
    sys.path entry, the prefixes, this package's folder), the system's libraries and the
    dynamic loader's cache. Not /etc, /home, /tmp or the server's data."""
    import renderfarm

    paths = [str(upload), str(Path(renderfarm.__file__).resolve().parents[1])]
    paths += [p for p in sys.path if p and os.path.isabs(p)]
    paths += [sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix]
    paths += ["/usr/lib", "/usr/lib64", "/usr/local/lib", "/lib", "/lib64", "/etc/ld.so.cache"]
    paths += ["/sys/devices/system/cpu"]  # the CPUs a thread pool sizes itself by
    return list(dict.fromkeys(os.path.realpath(p) for p in paths))


def _preload() -> None:
    """Load what the conversion uses before the child confines itself (the libraries are
    readable afterwards too; this only keeps their first use out of the confined part)."""
    import OpenImageIO  # noqa: F401
    from pxr import Ar, Plug, Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel, UsdVol  # noqa: F401

    Plug.Registry()
    for extension in ("usda", "usdc", "usdz"):
        Sdf.FileFormat.FindByExtension(extension)


def main(argv: list[str]) -> int:
    """The child: convert DIR/ROOT into OUT; print {"ok", "warnings", "camera"} or
    {"ok": false, "error", "field"} as the last line of stdout."""
    upload, root_layer, out = Path(argv[0]), argv[1], Path(argv[2])
    for key in [k for k in os.environ if k.startswith(("PXR_", "TF_"))]:
        del os.environ[key]
    try:
        from ..domain.scenes.usd_convert import convert_stage

        _preload()
        confinement = confine(readable_paths(upload), [out.parent])
        root = Path(os.path.realpath(upload))
        conversion = convert_stage(root / root_layer, root, Path(os.path.realpath(out.parent)))
        out.write_bytes(conversion.glb)
        environment = None
        if conversion.environment is not None:
            env = conversion.environment
            (out.parent / "environment").write_bytes(env["data"])
            environment = {k: env[k] for k in ("filename", "intensity", "rotation_deg", "prim")}
    except SceneError as e:
        print(json.dumps({"ok": False, "error": e.message, "field": e.field}))
        return 1
    answer = {"ok": True, "warnings": conversion.warnings, "camera": conversion.camera}
    print(json.dumps({**answer, "environment": environment, "confinement": confinement}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

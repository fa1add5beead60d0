"""Job settings: names, defaults, limits and validation shared by REST, gRPC and the CLI.

Every setting a job accepts is declared once here (SETTINGS). The REST API, the gRPC API and the
CLI flags are all derived from this table, so they cannot drift apart.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, fields
from typing import Any

from ..errors import SettingsError

SAMPLERS = ("sobol", "halton", "stratified", "independent")
INTEGRATORS = ("path", "direct", "ao")


# Worker tags (renderfarm-worker connect --tag) and a job's require_tags: the worker checks the
# same rule in worker/src/main.cpp.
TAG_PATTERN = re.compile(r"[a-z0-9][a-z0-9._-]{0,63}")
MAX_TAGS = 32


def check_tags(field: str, value: Any) -> list[str]:
    """A list of tags (or a text of tags separated by commas or spaces, a form field), each
    1..64 of a-z, 0-9, '.', '_', '-' starting with a letter or digit; sorted, once each."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise SettingsError(field, f"{field} must be a list of tags")
    if len(value) > MAX_TAGS:
        raise SettingsError(field, f"{field} has more than {MAX_TAGS} tags")
    for v in value:
        if not TAG_PATTERN.fullmatch(v):
            raise SettingsError(
                field,
                f"{field}: bad tag {v[:80]!r}: 1 to 64 of a-z, 0-9, '.', '_', '-', "
                "starting with a letter or digit",
            )
    return sorted(set(value))


@dataclass(frozen=True)
class Limits:
    """Server-side limits on what a job may ask for (configurable, see config.Settings)."""

    max_width: int = 16384
    max_height: int = 16384
    max_pixels: int = 64 * 2**20
    max_spp: int = 1 << 20
    max_time_limit_s: float = 7 * 24 * 3600.0
    max_job_memory_bytes: int = 1 << 62  # estimated accumulator memory (job_memory_bytes)


# What a job's tile accumulators take (merge.TileAccumulator): float64 RGB sum, mean luminance
# and two M2 sums, float32 albedo and normal sums (72 bytes a pixel), and the bookkeeping of
# each tile (its accumulator objects, scheduling state and dispatch entries: under 4 KB,
# measured with tracemalloc in server/tests/test_jobspec.py).
ACCUMULATOR_BYTES_PER_PIXEL = 72
TILE_OVERHEAD_BYTES = 4096


def job_memory_bytes(width: int, height: int, tile_size: int) -> int:
    """Estimated memory of a job's accumulators, whether in RAM or spilled to the scratch
    directory (infra/spill.py), from its size and tile size."""
    tiles = math.ceil(width / tile_size) * math.ceil(height / tile_size)
    return ACCUMULATOR_BYTES_PER_PIXEL * width * height + TILE_OVERHEAD_BYTES * tiles


# What denoising a frame takes (images.denoise_frame): float32 colour, albedo, normal and output
# of the whole frame (48 bytes a pixel; 60 leaves room for a copy of non-finite colour and the
# bands' temporaries) and Open Image Denoise's own scratch memory, held under
# DENOISE_SCRATCH_MB by its maxMemoryMB parameter (beyond it, it denoises in overlapping
# tiles). Peak resident memory over the loaded library, measured: 498 MB for 1024x1024 and
# 612 MB for 2048x2048 (about 450 MB of scratch and the 48 bytes a pixel).
DENOISE_BYTES_PER_PIXEL = 60
DENOISE_SCRATCH_MB = 512


def denoise_memory_bytes(width: int, height: int) -> int:
    """Estimated memory of denoising a width x height frame."""
    return DENOISE_BYTES_PER_PIXEL * width * height + DENOISE_SCRATCH_MB * 2**20


@dataclass(frozen=True)
class Setting:
    name: str
    kind: type
    default: Any
    help: str


# The one table of job settings. Order is the order shown in docs and --help.
SETTINGS: tuple[Setting, ...] = (
    Setting("width", int, 512, "image width in pixels"),
    Setting("height", int, 512, "image height in pixels"),
    Setting("tile_size", int, 64, "edge of the square tiles the image is split into, in pixels"),
    Setting("sampler", str, "sobol", "sample generator: " + ", ".join(SAMPLERS)),
    Setting("integrator", str, "path", "light transport algorithm: " + ", ".join(INTEGRATORS)),
    Setting("max_depth", int, 8, "maximum number of bounces of a path"),
    Setting("seed", int, 0, "seed of every random number; same seed, same image"),
    Setting(
        "noise_threshold",
        float,
        0.02,
        "a tile stops once its relative error is below this; 0 renders max_spp everywhere",
    ),
    Setting("min_spp", int, 16, "samples per pixel a tile renders before it may stop on noise"),
    Setting("max_spp", int, 1024, "samples per pixel at which a tile stops regardless of noise"),
    Setting("time_limit_s", float, 0.0, "wall-clock limit of the job in seconds; 0 = none"),
    Setting("priority", int, 0, "jobs with higher priority are rendered first"),
    Setting(
        "environment",
        str,
        "",
        "sha256 of a stored equirectangular .hdr/.exr environment map (uploaded with the job); "
        "empty = black background",
    ),
    Setting("environment_intensity", float, 1.0, "radiance scale of the environment map"),
    Setting("environment_rotation_deg", float, 0.0, "rotation of the environment about +Y"),
    Setting("aperture_radius", float, 0.0, "thin lens radius in metres; 0 = pinhole camera"),
    Setting("focus_distance", float, 0.0, "distance in focus in metres (needed with an aperture)"),
    Setting(
        "denoise",
        bool,
        False,
        "add a denoised layer (Intel Open Image Denoise) beside the unbiased image",
    ),
)
SETTING_NAMES = tuple(s.name for s in SETTINGS)
# `spp` is accepted as a shorthand for max_spp (the CLI's --spp), never stored.
ALIASES = {"spp": "max_spp"}


@dataclass(frozen=True)
class JobSettings:
    width: int = 512
    height: int = 512
    tile_size: int = 64
    sampler: str = "sobol"
    integrator: str = "path"
    max_depth: int = 8
    seed: int = 0
    noise_threshold: float = 0.02
    min_spp: int = 16
    max_spp: int = 1024
    time_limit_s: float = 0.0
    priority: int = 0
    environment: str = ""
    environment_intensity: float = 1.0
    environment_rotation_deg: float = 0.0
    aperture_radius: float = 0.0
    focus_distance: float = 0.0
    denoise: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


assert tuple(f.name for f in fields(JobSettings)) == SETTING_NAMES
assert all(getattr(JobSettings(), s.name) == s.default for s in SETTINGS)


def _coerce(name: str, kind: type, value: Any) -> Any:
    field = f"settings.{name}"
    if kind is bool:
        # JSON true/false; "true"/"false" from a form field or the command line.
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        raise SettingsError(field, f"{field} must be true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise SettingsError(field, f"{field} must be an integer, got {value!r}")
        try:
            as_float = float(value)
        except (ValueError, OverflowError):
            raise SettingsError(field, f"{field} must be an integer, got {value!r}") from None
        if not math.isfinite(as_float) or as_float != int(as_float):
            raise SettingsError(field, f"{field} must be an integer, got {value!r}")
        return int(as_float)
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise SettingsError(field, f"{field} must be a number, got {value!r}")
        try:
            number = float(value)
        except (ValueError, OverflowError):
            raise SettingsError(field, f"{field} must be a number, got {value!r}") from None
        if not math.isfinite(number):
            raise SettingsError(field, f"{field} must be finite, got {value!r}")
        return number
    if not isinstance(value, str):
        raise SettingsError(field, f"{field} must be a string, got {value!r}")
    return value.strip().lower()


def parse_settings(raw: dict[str, Any] | None, limits: Limits = Limits()) -> JobSettings:
    """Validate user-supplied settings, fill in defaults and return them.

    Raises SettingsError naming the first offending field: unknown names, wrong types,
    out-of-range values and limits.
    """
    raw = dict(raw or {})
    values: dict[str, Any] = {}
    for key, value in raw.items():
        if not isinstance(key, str):
            raise SettingsError("settings", f"setting names must be strings, got {key!r}")
        name = ALIASES.get(key, key)
        if name not in SETTING_NAMES:
            raise SettingsError(
                f"settings.{key}",
                f"unknown setting {key!r}; known settings: {', '.join(SETTING_NAMES)}",
            )
        if value is None:
            continue
        kind = next(s.kind for s in SETTINGS if s.name == name)
        coerced = _coerce(key, kind, value)
        if name in values and values[name] != coerced:
            alias = key if key in ALIASES else next(a for a, n in ALIASES.items() if n == name)
            raise SettingsError(
                f"settings.{alias}",
                f"settings.{alias} is short for settings.{ALIASES[alias]}; they disagree",
            )
        values[name] = coerced
    # An unspecified min_spp never exceeds the requested max_spp (so `--spp 4` just works).
    if "min_spp" not in values and "max_spp" in values:
        values["min_spp"] = max(1, min(JobSettings.min_spp, values["max_spp"]))
    settings = JobSettings(**values)
    try:
        _check_ranges(settings, limits)
    except SettingsError as e:
        # Name the field the way the caller spelled it (spp rather than max_spp).
        for alias, name in ALIASES.items():
            if alias in raw and name not in raw and e.field == f"settings.{name}":
                raise SettingsError(
                    f"settings.{alias}", e.message.replace(f"settings.{name}", f"settings.{alias}")
                ) from None
        raise
    return settings


def _require(ok: bool, name: str, message: str) -> None:
    if not ok:
        raise SettingsError(f"settings.{name}", f"settings.{name} {message}")


def _check_ranges(s: JobSettings, limits: Limits) -> None:
    _require(1 <= s.width <= limits.max_width, "width", f"must be in 1..{limits.max_width}")
    _require(1 <= s.height <= limits.max_height, "height", f"must be in 1..{limits.max_height}")
    _require(
        s.width * s.height <= limits.max_pixels,
        "width",
        f"width x height must be at most {limits.max_pixels} pixels",
    )
    _require(8 <= s.tile_size <= 512, "tile_size", "must be in 8..512")
    need = job_memory_bytes(s.width, s.height, s.tile_size)
    _require(
        need <= limits.max_job_memory_bytes,
        "width",
        f"x settings.height = {s.width} x {s.height} needs about {need / 2**20:.0f} MB of "
        f"accumulators ({ACCUMULATOR_BYTES_PER_PIXEL} bytes a pixel and "
        f"{TILE_OVERHEAD_BYTES} a tile), more than the server's limit of "
        f"{limits.max_job_memory_bytes / 2**20:.0f} MB (RENDERFARM_MAX_JOB_MEMORY_MB)",
    )
    _require(s.sampler in SAMPLERS, "sampler", f"must be one of {', '.join(SAMPLERS)}")
    _require(s.integrator in INTEGRATORS, "integrator", f"must be one of {', '.join(INTEGRATORS)}")
    _require(1 <= s.max_depth <= 1024, "max_depth", "must be in 1..1024")
    _require(0 <= s.seed < 2**63, "seed", "must be in 0..2^63-1")
    _require(0.0 <= s.noise_threshold <= 10.0, "noise_threshold", "must be in 0..10")
    _require(1 <= s.max_spp <= limits.max_spp, "max_spp", f"must be in 1..{limits.max_spp}")
    _require(1 <= s.min_spp <= s.max_spp, "min_spp", f"must be in 1..max_spp ({s.max_spp})")
    _require(
        0.0 <= s.time_limit_s <= limits.max_time_limit_s,
        "time_limit_s",
        f"must be in 0..{limits.max_time_limit_s:g}",
    )
    _require(-1000 <= s.priority <= 1000, "priority", "must be in -1000..1000")
    _require(
        s.environment == "" or re.fullmatch(r"[0-9a-f]{64}", s.environment) is not None,
        "environment",
        "must be the sha256 of a stored environment map (64 hex digits)",
    )
    _require(0.0 < s.environment_intensity <= 1e6, "environment_intensity", "must be in (0, 1e6]")
    _require(
        -360.0 <= s.environment_rotation_deg <= 360.0,
        "environment_rotation_deg",
        "must be in -360..360",
    )
    _require(0.0 <= s.aperture_radius <= 100.0, "aperture_radius", "must be in 0..100")
    _require(0.0 <= s.focus_distance <= 1e6, "focus_distance", "must be in 0..1e6")
    _require(
        s.aperture_radius == 0.0 or s.focus_distance > 0.0,
        "focus_distance",
        "must be positive when aperture_radius is set",
    )
    if s.denoise:  # the whole frame beside the accumulators (images.DenoiseFrame)
        frame = denoise_memory_bytes(s.width, s.height)
        need = frame + job_memory_bytes(s.width, s.height, s.tile_size)
        _require(
            need <= limits.max_job_memory_bytes,
            "denoise",
            f"needs the whole {s.width} x {s.height} frame in memory beside the accumulators: "
            f"about {frame / 2**20:.0f} MB ({DENOISE_BYTES_PER_PIXEL} bytes a pixel and "
            f"{DENOISE_SCRATCH_MB} MB of scratch), {need / 2**20:.0f} MB in all, more than the "
            f"server's limit of {limits.max_job_memory_bytes / 2**20:.0f} MB "
            "(RENDERFARM_MAX_JOB_MEMORY_MB); render without it or smaller",
        )


# ------------------------------------------------------------------ request fields beside settings
# Shared by REST and gRPC, so both refuse the same input with the same field named.
JOB_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
SHA256_PATTERN = re.compile(r"[0-9a-f]{64}")


def check_text(field: str, value: str, max_length: int = 1000) -> str:
    """A free-text request field (job name, file name): no NUL or control characters."""
    if len(value) > max_length:
        raise SettingsError(field, f"{field} is longer than {max_length} characters")
    if any(ord(c) < 32 and c not in "\t" for c in value):
        raise SettingsError(field, f"{field} contains a control character")
    return value


def check_sha256(field: str, value: str) -> str:
    """A scene or environment hash: 64 lowercase hex digits (upper case is accepted)."""
    digest = value.strip().lower()
    if not SHA256_PATTERN.fullmatch(digest):
        raise SettingsError(field, f"{field} must be a sha256 (64 hex digits), got {value[:80]!r}")
    return digest


def is_job_id(value: str) -> bool:
    """Whether `value` could name a job (ids are 12 hex digits; older ones up to 64 of
    [A-Za-z0-9_-]). Anything else is answered "not found" without asking the database."""
    return JOB_ID_PATTERN.fullmatch(value) is not None

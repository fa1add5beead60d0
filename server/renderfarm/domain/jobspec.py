"""Job settings: names, defaults, limits and validation shared by REST, gRPC and the CLI.

Every setting a job accepts is declared once here (SETTINGS): name, type (enumerations are
StrEnums), default, range, unit, help and its field in renderfarm.v1.RenderSettings. From the table
come the JobSettings dataclass, the validation below, the REST models and /api/v1/settings (and
so the OpenAPI document, the dashboard's generated types and the Blender add-on's fields), the CLI
flags and docs/settings.md (`python -m renderfarm settings --markdown`); the proto and the worker's
reading of it are held to it by server/tests/test_settings_schema.py.

One module although over 500 lines: the table is most of it, one row per setting, and the
validation beside it reads the same rows; splitting them would put a setting in two places.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field, make_dataclass
from enum import EnumMeta, StrEnum
from typing import Any

from ..errors import SettingsError
from . import channels
from .frames import ALL_VARIANTS, check_animation_selection, parse_frames, parse_shutter

# Worker tags (renderfarm-worker connect --tag) and a job's require_tags: the worker checks the
# same rule in worker/src/programs/main.cpp.
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
    max_frames: int = 10000  # frames one job may name (settings.frames)
    max_job_memory_bytes: int = 1 << 62  # estimated accumulator memory (job_memory_bytes)


# What a job's tile accumulators take (merge.TileAccumulator): the arrays of its rows of the
# channel table (channels.py; 76 bytes a pixel without `aovs`: float64 RGB sum, mean luminance
# and two M2 sums, float32 coverage, albedo and normal sums; depth adds 4, position 12), and
# the bookkeeping of each tile (its accumulator objects, scheduling state and dispatch entries:
# under 4 KB, measured with tracemalloc in server/tests/test_jobspec.py).
ACCUMULATOR_BYTES_PER_PIXEL = channels.bytes_per_pixel()
TILE_OVERHEAD_BYTES = 4096


# An animation frame of at most this many pixels (and sides up to CHUNK_MAX_SIDE, the largest
# tile) is one tile when the job does not set tile_size: on 2 one-thread workers, 12 frames of
# 64x48 and 128x96 rendered 13-20 % faster as chunks than as 64-pixel tiles; from 256x192 on a
# chunk was no faster and delayed the first finished frame 5 times (bench/frame_chunks.py).
CHUNK_PIXELS = 128 * 128
CHUNK_MAX_SIDE = 512


def job_memory_bytes(
    width: int, height: int, tile_size: int, aovs: str = "", groups: tuple[str, ...] = ()
) -> int:
    """Estimated memory of a job's accumulators, whether in RAM or spilled to the scratch
    directory (infra/spill.py), from its size, tile size, the outputs its `aovs` turns on and
    its light groups (with light_groups: at least the environment's)."""
    tiles = math.ceil(width / tile_size) * math.ceil(height / tile_size)
    per_pixel = channels.layout_for(aovs, groups=groups).bytes_per_pixel()
    return per_pixel * width * height + TILE_OVERHEAD_BYTES * tiles


def settings_memory_bytes(s: JobSettings) -> int:
    """job_memory_bytes of a job's settings (one image)."""
    return channels.job_layout(s).bytes_per_pixel() * s.width * s.height + (
        TILE_OVERHEAD_BYTES * math.ceil(s.width / s.tile_size) * math.ceil(s.height / s.tile_size)
    )


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


class Sampler(StrEnum):
    """Sample generators (the worker's sampling/samplers.h; proto renderfarm.v1.Sampler)."""

    SOBOL = "sobol"
    HALTON = "halton"
    STRATIFIED = "stratified"
    INDEPENDENT = "independent"


class Integrator(StrEnum):
    """Light transport algorithms (the worker's render/integrators.h; proto v1.Integrator)."""

    PATH = "path"
    DIRECT = "direct"
    AO = "ao"


class NoiseMetric(StrEnum):
    """What a noise threshold bounds (proto renderfarm.v1.NoiseMetric)."""

    RELATIVE = "relative"
    DISPLAY = "display"


class Adaptive(StrEnum):
    """Where a job with a noise threshold decides to stop (proto renderfarm.v1.Adaptive)."""

    TILE = "tile"
    PIXEL = "pixel"
    PIXEL_MSE = "pixel_mse"


SAMPLERS = tuple(m.value for m in Sampler)
INTEGRATORS = tuple(m.value for m in Integrator)


@dataclass(frozen=True)
class Setting:
    """One job setting: everything the APIs, the CLI, the dashboard, the Blender add-on, the
    worker's message and the docs know of it (server/tests/test_settings_schema.py holds the
    proto, the worker and docs/settings.md to it).

    kind: int, float, bool, str or an enumeration (a StrEnum: its values are the choices).
    proto: the field number in renderfarm.v1.RenderSettings (proto_name when the field is
    named otherwise). minimum/maximum: the range (open at the bottom when exclusive_minimum);
    limit: a Limits attribute that bounds it instead of `maximum` (the server's configuration).
    bounded_by: another setting that bounds it above instead (checked after that one).
    worker: whether workers read it (else the server alone acts on it).
    derived: filled in by the server (from the scene), not chosen: forms leave it out."""

    name: str
    kind: type
    default: Any
    help: str
    proto: int
    proto_name: str = ""
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    limit: str = ""
    bounded_by: str = ""  # another setting that bounds it above (min_spp <= max_spp)
    unit: str = ""
    worker: bool = True
    derived: bool = False

    @property
    def field(self) -> str:
        """The RenderSettings field."""
        return self.proto_name or self.name

    @property
    def choices(self) -> tuple[str, ...]:
        """The values of an enumerated setting; () for any other."""
        return tuple(m.value for m in self.kind) if isinstance(self.kind, EnumMeta) else ()

    @property
    def type_name(self) -> str:
        """int, float, bool or str (an enumeration is a str with choices)."""
        return "str" if self.choices else self.kind.__name__


# The one table of job settings. Order is the order shown in docs and --help.
SETTINGS: tuple[Setting, ...] = (
    Setting("width", int, 512, "image width in pixels", 1,
            minimum=1, limit="max_width", unit="px"),
    Setting("height", int, 512, "image height in pixels", 2,
            minimum=1, limit="max_height", unit="px"),
    Setting("tile_size", int, 64,
            "edge of the square tiles the image is split into, in pixels; an animation whose "
            "frames have at most 16384 pixels gets one tile per frame unless it is set", 3,
            minimum=8, maximum=512, unit="px", worker=False),
    Setting("sampler", Sampler, "sobol",
            "sample generator: sobol (Owen-scrambled Sobol', randomized per pixel), halton "
            "(random digit permutations per pixel), stratified (jittered per batch, Latin "
            "hypercube padding) or independent", 19),
    Setting("integrator", Integrator, "path",
            "light transport: path (path tracing with next-event estimation, MIS and Russian "
            "roulette), direct (one bounce: emission, light and BSDF sampling with MIS) or ao "
            "(ambient occlusion)", 20),
    Setting("max_depth", int, 8, "maximum number of bounces of a path", 6,
            minimum=1, maximum=1024),
    Setting("seed", int, 0, "seed of every random number; same seed, same image", 7,
            minimum=0, maximum=2**63 - 1),
    Setting("noise_threshold", float, 0.02,
            "a tile stops once its relative error is below this; 0 renders max_spp everywhere", 8,
            minimum=0.0, maximum=10.0, worker=False),
    Setting("adaptive", Adaptive, "tile",
            "with a noise threshold, where sampling stops: tile (a tile stops when the RMS of its "
            "pixels' relative errors is below the threshold), pixel (from the 64th sample on, "
            "each pixel stops when its own error, averaged with its 3x3 neighbours', is below the "
            "threshold, and its tile when every pixel has; the `spp` layer shows each pixel's "
            "samples) or pixel_mse (per pixel, the samples where they lower the image's mean "
            "squared error most for the time: a pixel with n samples stops below threshold x "
            "sqrt(n / 64), so noisy pixels end noisier than the threshold and the image's "
            "error is least) (docs/usage.md, Adaptive sampling)", 29, worker=False),
    Setting("noise_metric", NoiseMetric, "relative",
            "what noise_threshold bounds: relative (a pixel's standard error over its brightness, "
            "for images that will be graded or composited) or display (the standard error of the "
            "pixel as a viewer sees it, sRGB-encoded and clipped to 0..1: dark pixels need less, "
            "pixels brighter than white none; a threshold of 0.002 is half an 8-bit level) "
            "(docs/usage.md, Adaptive sampling)", 30, worker=False),
    Setting("min_spp", int, 16,
            "samples per pixel a tile renders before it may stop on noise", 9,
            minimum=1, bounded_by="max_spp", worker=False),
    Setting("max_spp", int, 1024,
            "samples per pixel at which a tile stops regardless of noise (`spp` is an alias)", 10,
            minimum=1, limit="max_spp", worker=False),
    Setting("time_limit_s", float, 0.0, "wall-clock limit of the job in seconds; 0 = none", 11,
            minimum=0.0, limit="max_time_limit_s", unit="s", worker=False),
    Setting("priority", int, 0,
            "jobs with higher priority are rendered first; equal priorities share the farm", 12,
            minimum=-1000, maximum=1000, worker=False),
    Setting("environment", str, "",
            "environment map: the sha256 of a stored equirectangular .hdr/.exr, uploaded with the "
            "job as the multipart file `environment` (the CLI's --environment FILE does); empty "
            "= black background", 13, proto_name="environment_sha256"),
    Setting("environment_intensity", float, 1.0, "radiance scale of the environment map", 14,
            minimum=0.0, maximum=1e6, exclusive_minimum=True),
    Setting("environment_rotation_deg", float, 0.0,
            "rotation of the environment map about the world +Y axis, degrees", 15,
            minimum=-360.0, maximum=360.0, unit="deg"),
    Setting("aperture_radius", float, 0.0, "thin lens radius in metres; 0 is a pinhole camera", 16,
            minimum=0.0, maximum=100.0, unit="m"),
    Setting("focus_distance", float, 0.0,
            "distance of the plane in focus, metres; required when aperture_radius > 0", 17,
            minimum=0.0, maximum=1e6, unit="m"),
    Setting("denoise", bool, False,
            "add a `denoised` layer (Intel Open Image Denoise of the colour, with the albedo and "
            "normal as guides) beside the unbiased image, which stays as it is", 18,
            worker=False),
    Setting("frames", str, "",
            "frames of an animation to render: 1-120, 1-120x2 (every 2nd), 1,5,10-20; frame f is "
            "glTF time f / fps; at most 10000 frames (`RENDERFARM_MAX_FRAMES`). Empty: one still "
            "of the scene as stored, no animation", 21, worker=False),
    Setting("fps", float, 24.0,
            "frames per second of the animation: frame f is rendered at glTF time f / fps", 22,
            minimum=0.0, maximum=1000.0, exclusive_minimum=True, unit="1/s"),
    Setting("animation", str, "",
            "the glTF animations that drive the frames: a comma list of their indices or names "
            "(names are case-sensitive); empty = all of them", 23),
    Setting("shutter", str, "",
            "motion blur: the shutter's open and close times as fractions of a frame after the "
            "frame's time, OPEN,CLOSE with -1 <= OPEN < CLOSE <= 1 at most 1 apart (0,0.5: a "
            "half-frame shutter); each sample sees the scene at one time between them. Empty: "
            "closed, no motion blur. Needs frames", 24),
    Setting("variant", str, "",
            "KHR_materials_variants: the material variant to render, by its name "
            "(case-sensitive) or index; empty = the scene's default materials; all = every "
            "variant of the scene, one image each (as frames; not with frames)", 25),
    Setting("aovs", str, "",
            "outputs beside the image, each a layer of the EXR and a PNG layer: a list (or "
            "comma list) of " + ", ".join(channels.AOV_NAMES) + " (docs/usage.md, Outputs); "
            "each adds to the job's memory", 26, worker=False),
    Setting("light_groups", str, "",
            "the job's light groups when aovs names light_groups: filled in by the server from "
            "the scene (a value given is replaced), a JSON object of group name -> the glTF "
            "node indices in it, in the order of their layers, the environment last "
            "(docs/usage.md, Outputs)", 27, derived=True),
    Setting("guiding", bool, False,
            "path guiding: each worker first learns where the light comes from (a fixed set of "
            "training paths, the same on every worker) and then samples those directions beside "
            "the BSDF at diffuse surfaces; the image converges to the same mean, with less noise "
            "where indirect light comes from a small part of the sphere (docs/usage.md, Path "
            "guiding)", 28),
)  # fmt: skip
SETTING_NAMES = tuple(s.name for s in SETTINGS)
SETTING_BY_NAME = {s.name: s for s in SETTINGS}
# `spp` is accepted as a shorthand for max_spp (the CLI's --spp), never stored.
ALIASES = {"spp": "max_spp"}


def _to_dict(self) -> dict[str, Any]:
    return asdict(self)


# A job's settings with every default filled in: a frozen dataclass made from the table, so a
# setting is declared in one place. Enumerated settings hold their value (a str).
JobSettings = make_dataclass(
    "JobSettings",
    [(s.name, str if s.choices else s.kind, field(default=s.default)) for s in SETTINGS],
    frozen=True,
    namespace={"to_dict": _to_dict, "__module__": __name__},
)


# Limits an operator sets (config.Settings, environment RENDERFARM_<NAME>); the others are fixed.
CONFIGURABLE_LIMITS = ("max_width", "max_height", "max_spp", "max_frames")


def setting_docs(limits: Limits = Limits()) -> list[dict[str, Any]]:
    """Every setting as GET /api/v1/settings serves it: name, type, default, help, choices,
    range (a limit as this server is configured) and unit."""
    docs = []
    for s in SETTINGS:
        top = getattr(limits, s.limit) if s.limit else s.maximum
        if s.bounded_by:
            top = getattr(limits, SETTING_BY_NAME[s.bounded_by].limit)
        docs.append({
            "name": s.name, "type": s.type_name, "default": s.default, "help": s.help,
            "choices": list(s.choices), "minimum": s.minimum,
            "exclusive_minimum": s.exclusive_minimum, "maximum": top, "unit": s.unit,
            "derived": s.derived,
        })  # fmt: skip
    return docs


def _range_text(s: Setting) -> str:
    if s.choices:
        return " \\| ".join(f"`{c}`" for c in s.choices)
    if s.minimum is None:
        return ""
    if s.bounded_by:
        return f"{_number(s.minimum)}..`{s.bounded_by}`"
    if s.limit:  # the default limit, and the server setting that changes it, if any
        top = _number(getattr(Limits(), s.limit))
        if s.limit in CONFIGURABLE_LIMITS:
            top += f" (`RENDERFARM_{s.limit.upper()}`)"
    else:
        top = _number(s.maximum) if s.maximum is not None else ""
    if s.exclusive_minimum:
        return f"({_number(s.minimum)}, {top}]"
    return f"{_number(s.minimum)}..{top}" if top else f"at least {_number(s.minimum)}"


def settings_markdown() -> str:
    """The job settings table of docs/settings.md (generated: a test holds the file to it)."""
    rows = ["| setting | type | default | range | unit | worker | meaning |",
            "|---|---|---|---|---|---|---|"]  # fmt: skip
    for s in SETTINGS:
        default = json.dumps(s.default)
        rows.append(
            f"| `{s.name}` | {s.type_name} | `{default}` | {_range_text(s)} | {s.unit} | "
            f"{'yes' if s.worker else 'no'} | {s.help.replace('|', '/')} |"
        )
    return "\n".join(rows) + "\n"


# String settings whose case means something (animation names); the others are lowercased.
KEEP_CASE = frozenset({"animation", "variant", "light_groups"})


def _coerce(name: str, kind: type, value: Any, keep_case: bool = False) -> Any:
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
    if name == "light_groups":  # a JSON object (or its text), kept as compact JSON
        return _light_groups_value(field, value)
    if name == "aovs":  # a list (JSON) or a comma list, kept as the names in table order
        if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            value = ",".join(value)
        if not isinstance(value, str):
            raise SettingsError(field, f"{field} must be a list of names, got {value!r}")
        try:
            return ",".join(channels.parse_aovs(value.lower()))
        except ValueError as e:
            raise SettingsError(field, f"{field}: {e}") from None
    if not isinstance(value, str):
        raise SettingsError(field, f"{field} must be a string, got {value!r}")
    return value.strip() if keep_case else value.strip().lower()


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
        kind = SETTING_BY_NAME[name].kind
        coerced = _coerce(key, kind, value, keep_case=name in KEEP_CASE)
        if name in values and values[name] != coerced:
            alias = key if key in ALIASES else next(a for a, n in ALIASES.items() if n == name)
            raise SettingsError(
                f"settings.{alias}",
                f"settings.{alias} is short for settings.{ALIASES[alias]}; they disagree",
            )
        values[name] = coerced
    # Light groups belong to jobs that ask for them (the server fills them in from the scene).
    if "light_groups" not in str(values.get("aovs", "")).split(","):
        values.pop("light_groups", None)
    # An unspecified min_spp never exceeds the requested max_spp (so `--spp 4` just works).
    if "min_spp" not in values and "max_spp" in values:
        values["min_spp"] = max(1, min(JobSettings.min_spp, values["max_spp"]))
    # Small frames of an animation are sent whole, one tile ("chunk") per frame, unless the
    # caller chose a tile size (bench/frame_chunks.py; docs/animation.md, "Tiles or chunks").
    if values.get("frames") and "tile_size" not in values:
        width = values.get("width", JobSettings.width)
        height = values.get("height", JobSettings.height)
        if (
            isinstance(width, int)
            and isinstance(height, int)
            and (0 < width * height <= CHUNK_PIXELS and max(width, height) <= CHUNK_MAX_SIDE)
        ):
            values["tile_size"] = max(8, width, height)
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


def _light_groups_value(field: str, value: Any) -> str:
    """settings.light_groups as compact JSON: an object of group name -> node indices."""
    if isinstance(value, str):
        if not value:
            return ""
        try:
            value = json.loads(value)
        except ValueError:
            raise SettingsError(field, f"{field} must be a JSON object") from None
    ok = isinstance(value, dict) and all(
        isinstance(k, str) and isinstance(v, list)
        and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in v)
        for k, v in value.items()
    )  # fmt: skip
    if not ok:
        raise SettingsError(
            field, f"{field} must be an object of group name -> a list of glTF node indices"
        )
    return json.dumps(value, separators=(",", ":"))


def _number(v: float) -> str:
    """A bound as the messages write it: 512, 0.5, 1e6, 2^63-1."""
    if v == 2**63 - 1:
        return "2^63-1"
    if isinstance(v, int):
        return str(v)
    return f"{v:g}".replace("e+0", "e").replace("e+", "e")


def _check_range(s: JobSettings, setting: Setting, limits: Limits) -> None:
    """The table's range of one setting (its choices, minimum, maximum or server limit)."""
    value = getattr(s, setting.name)
    if setting.choices:
        _require(value in setting.choices, setting.name,
                 f"must be one of {', '.join(setting.choices)}")  # fmt: skip
        return
    if setting.minimum is None:
        return
    top = getattr(limits, setting.limit) if setting.limit else setting.maximum
    lo, hi = _number(setting.minimum), _number(top) if top is not None else ""
    if setting.exclusive_minimum:
        _require(setting.minimum < value <= top, setting.name, f"must be in ({lo}, {hi}]")
    elif top is None:
        _require(setting.minimum <= value, setting.name, f"must be at least {lo}")
    else:
        _require(setting.minimum <= value <= top, setting.name, f"must be in {lo}..{hi}")


def _check_ranges(s: JobSettings, limits: Limits) -> None:
    for setting in SETTINGS:
        if setting.bounded_by:  # checked after the setting that bounds it
            continue
        _check_range(s, setting, limits)
        if setting.name == "height":
            _require(
                s.width * s.height <= limits.max_pixels,
                "width",
                f"width x height must be at most {limits.max_pixels} pixels",
            )
        if setting.name == "tile_size":
            need = settings_memory_bytes(s)
            _require(
                need <= limits.max_job_memory_bytes,
                "width",
                f"x settings.height = {s.width} x {s.height} needs about {need / 2**20:.0f} MB "
                f"of accumulators ({channels.job_layout(s).bytes_per_pixel()} bytes a "
                "pixel with the outputs of settings.aovs, and "
                f"{TILE_OVERHEAD_BYTES} a tile), more than the server's limit of "
                f"{limits.max_job_memory_bytes / 2**20:.0f} MB (RENDERFARM_MAX_JOB_MEMORY_MB)",
            )
        for other in SETTINGS:
            if other.bounded_by == setting.name:
                value, top = getattr(s, other.name), getattr(s, setting.name)
                _require(
                    other.minimum <= value <= top,
                    other.name,
                    f"must be in {_number(other.minimum)}..{setting.name} ({top})",
                )
    _require(
        s.environment == "" or re.fullmatch(r"[0-9a-f]{64}", s.environment) is not None,
        "environment",
        "must be the sha256 of a stored environment map (64 hex digits)",
    )
    if s.frames:
        frame_count = len(parse_frames(s.frames, limits.max_frames))
        need = frame_count * settings_memory_bytes(s)
        _require(
            need <= limits.max_job_memory_bytes,
            "frames",
            f"names {frame_count} frames of {s.width} x {s.height}: about {need / 2**20:.0f} MB of "
            f"accumulators in all, more than the server's limit of "
            f"{limits.max_job_memory_bytes / 2**20:.0f} MB (RENDERFARM_MAX_JOB_MEMORY_MB); "
            "split the range into several jobs",
        )
    check_animation_selection(s.animation)
    _require(len(s.variant) <= 200, "variant", "is longer than 200 characters")
    _require(
        not (s.variant == ALL_VARIANTS and s.frames),
        "variant",
        f'"{ALL_VARIANTS}" renders every variant of the scene as a still, one image each, '
        "and cannot be combined with settings.frames: submit one job per variant with frames",
    )
    if parse_shutter(s.shutter) is not None:
        _require(
            bool(s.frames),
            "shutter",
            "needs settings.frames: a still is the scene as stored, with nothing that moves "
            "(leave shutter empty, or render frames)",
        )
    for split, by in (("lobes", "the lobes of the first hit"), ("light_groups", "light source")):
        _require(
            not (s.integrator == Integrator.AO and split in s.aovs.split(",")),
            "aovs",
            f"names {split}, which split the radiance by {by}, and the ao integrator renders "
            f"no radiance: use integrator path or direct, or leave {split} out",
        )
    _require(
        s.aperture_radius == 0.0 or s.focus_distance > 0.0,
        "focus_distance",
        "must be positive when aperture_radius is set",
    )
    if s.denoise:  # the whole frame beside the accumulators (images.DenoiseFrame)
        frame = denoise_memory_bytes(s.width, s.height)
        need = frame + settings_memory_bytes(s)
        _require(
            need <= limits.max_job_memory_bytes,
            "denoise",
            f"needs the whole {s.width} x {s.height} frame in memory beside the accumulators: "
            f"about {frame / 2**20:.0f} MB ({DENOISE_BYTES_PER_PIXEL} bytes a pixel and "
            f"{DENOISE_SCRATCH_MB} MB of scratch), {need / 2**20:.0f} MB in all, more than the "
            f"server's limit of {limits.max_job_memory_bytes / 2**20:.0f} MB "
            "(RENDERFARM_MAX_JOB_MEMORY_MB); render without it or smaller",
        )


def check_variant_images(s: JobSettings, count: int, limits: Limits) -> None:
    """A job of every variant (settings.variant "all") renders `count` images, each with its
    own accumulators, as frames do: held to the frames' limits (RENDERFARM_MAX_FRAMES and the
    job's memory), SettingsError naming settings.variant otherwise. Nothing to check for other
    jobs (count 0)."""
    if count == 0:
        return
    _require(
        count <= limits.max_frames,
        "variant",
        f'"{ALL_VARIANTS}": the scene has {count} variants, more images than one job may '
        f"render ({limits.max_frames}, RENDERFARM_MAX_FRAMES); name them one job each",
    )
    need = count * settings_memory_bytes(s)
    _require(
        need <= limits.max_job_memory_bytes,
        "variant",
        f'"{ALL_VARIANTS}": {count} variants of {s.width} x {s.height} need about '
        f"{need / 2**20:.0f} MB of accumulators in all, more than the server's limit of "
        f"{limits.max_job_memory_bytes / 2**20:.0f} MB (RENDERFARM_MAX_JOB_MEMORY_MB); "
        "name the variants one job each",
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

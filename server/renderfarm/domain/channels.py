"""The per-pixel channels of a job: one table from which everything per pixel derives (#40).

A row (Channel) is one per-pixel quantity: what the workers accumulate for it, how batches of
it are merged, the arrays the server keeps for it (in RAM, in spill files and in checkpoints,
in this order), the layers of the images it gives and their EXR channel names, and what turns it
on. What derives from the table:

- the accumulator's arrays and their bytes a pixel (merge.TileAccumulator, jobspec's memory
  estimate, spill slots, the tile cache's budget);
- checkpoint blobs, which carry a header naming their arrays (checkpoint_bytes / read_blob:
  nothing is recognised by its length but blobs of servers from before the header);
- the EXR's channels and the layers of images.png (infra/images.py), the CLI's `--layer`
  (cli/commands.py), the REST API's `layer` values and through them the dashboard's layer
  switch (web/openapi.json), and the outputs table of docs/usage.md (layers_markdown).

server/tests/test_channel_table.py fails when any of them disagrees with the table.

One module although over 500 lines: the rows, the layouts they make for a job, what is generated
from them and the checkpoint blobs' header are one format, versioned together (TABLE_VERSION);
most of the length is the rows themselves, whose help texts are the docs'.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import struct
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

# Bump when a row's arrays change meaning or layout: stored in every checkpoint blob's header.
TABLE_VERSION = 1


class Accumulate(StrEnum):
    """How a row's batches are merged on the server."""

    # A sum over the row's window of samples, added batch by batch in batch order.
    SUM = "sum"
    # The luminance statistics of the radiance (`rgb`): its running mean and the within- and
    # between-batch M2 (merge.py, Chan et al.), merged by the fused kernel with the RGB sum.
    MOMENTS = "moments"
    # A count of samples (coverage: those whose camera ray hit geometry).
    COUNT = "count"
    # The value of each pixel's first sample only (a first-hit quantity such as depth, as
    # Blender's data passes take it): a sum over a window of one sample, which the schedule's
    # first batch is (tiling.py).
    FIRST = "first"
    # Ranked ID coverage (Cryptomatte, domain/cryptomatte.py): per pixel the labels the most
    # samples' first hits had, with their counts, as (label, count) uint32 pairs; merged by
    # adding the counts of equal labels and keeping the largest (cryptomatte.merge_ranked).
    RANKED = "ranked"
    # Nothing accumulated: computed at output from other rows (the denoised image).
    DERIVED = "derived"
    # Kept by the server, never on the wire: per-pixel adaptive sampling's state (each pixel's
    # merged samples and the last batch it renders, merge.TileAccumulator).
    SERVER = "server"


class Display(StrEnum):
    """How a layer is shown in a PNG (images.py) and the dashboard."""

    COLOUR = "colour"  # linear RGB, sRGB-encoded and clamped to [0, 1]
    SIGNED = "signed"  # a unit vector, x * 0.5 + 0.5
    GREY = "grey"  # one value, normalised to the image's largest finite value
    # One value, normalised to the image's largest value below BACKGROUND_DEPTH (a depth: what
    # the camera ray missed shows white).
    DEPTH = "depth"
    # Each component normalised to its range over the pixels the camera ray hit (a position);
    # black where it missed.
    RANGE = "range"
    # A motion (Blender's Vector): the motion to the next frame in image coordinates, (-Z, W),
    # as red (x) and green (y, down) around grey, normalised to its largest magnitude.
    FLOW = "flow"
    # An integer label: a colour of its own for each value (a hash of it), black for 0.
    LABEL = "label"
    # Ranked labels (Cryptomatte): each label's colour (as LABEL) weighted by its coverage.
    MATTE = "matte"


@dataclass(frozen=True)
class Array:
    """One per-pixel array the server keeps: name, dtype (little-endian numpy) and components."""

    name: str
    dtype: str
    components: int = 1

    @property
    def bytes_per_pixel(self) -> int:
        return np.dtype(self.dtype).itemsize * self.components

    def shape(self, width: int, height: int) -> tuple[int, ...]:
        return (height, width) if self.components == 1 else (height, width, self.components)


@dataclass(frozen=True)
class Layer:
    """One layer of a job's images: `images.png?layer=NAME`, `renderfarm get --layer NAME`, the
    dashboard's switch (name None: EXR channels only)."""

    name: str | None
    exr: tuple[str, ...]
    label: str
    help: str
    display: Display = Display.COLOUR
    # The arrays an image of the layer reads (None: its row's own).
    reads: tuple[str, ...] | None = None


@dataclass(frozen=True)
class Channel:
    name: str
    help: str
    accumulate: Accumulate
    # The BatchResult field (TileResult's, for workers from before the table) the server
    # merges it from ("": none).
    wire: str
    store: tuple[Array, ...]
    layers: tuple[Layer, ...]
    # 0: every sample; else only each pixel's first `window` samples (a batch boundary of the
    # schedule, tiling.py), and its arrays are checkpointed apart, only while they change.
    window: int = 0
    # The job setting that turns the row on ("": always on), and for `aovs` the name in its
    # list that does.
    setting: str = ""
    aov: str = ""
    # What a result carries of it (a ChannelBlock): components per pixel and their type; 0
    # components: nothing (a row the server derives).
    wire_components: int = 0
    wire_type: str = "<f4"
    # A row of one block per light group of the job (Layout.groups): its array's and the
    # wire's components are these times the group count, and its layer is one per group
    # (light_group_layers); the table's row is the template a job's layout resolves.
    per_group: bool = False


AOV_SAMPLES = 16  # albedo and normal cover a pixel's first 16 samples (tiling.AOV_SAMPLES)
CRYPTO_RANKS = 6  # (label, count) pairs a Cryptomatte row keeps per pixel (cryptomatte.RANKS)


def _crypto_channels(type_name: str) -> tuple[str, ...]:
    """A Cryptomatte type's EXR channels: {type}00.R (rank 0's ID), .G (its coverage), .B, .A
    (rank 1's), then {type}01 and {type}02."""
    return tuple(
        f"{type_name}{level:02d}.{c}" for level in range(CRYPTO_RANKS // 2) for c in "RGBA"
    )


# The `lobes` rows (#40): the radiance split by what the path did at its first scattering
# vertex, each summing with the others to the `rgb` row's radiance (name, label, help).
LOBES: tuple[tuple[str, str, str], ...] = (
    (
        "diffuse_direct",
        "Diffuse direct",
        "light sources reached from the first hit through its diffuse lobes (Lambert base, "
        "diffuse transmission, sheen), one bounce: Blender's DiffDir without the colour factor",
    ),
    (
        "diffuse_indirect",
        "Diffuse indirect",
        "everything else the first hit's diffuse lobes bring (two bounces and more): Blender's "
        "DiffInd without the colour factor",
    ),
    (
        "glossy_direct",
        "Glossy direct",
        "light sources reached through the first hit's reflective specular lobes (dielectric and "
        "metal GGX, clear coat, the glass's reflection): Blender's GlossDir without the colour "
        "factor",
    ),
    (
        "glossy_indirect",
        "Glossy indirect",
        "everything else the first hit's reflective specular lobes bring: Blender's GlossInd "
        "without the colour factor",
    ),
    (
        "transmission_direct",
        "Transmission direct",
        "light sources seen through the first hit's glass (KHR_materials_transmission, smooth "
        "or rough), one bounce: Blender's TransDir without the colour factor",
    ),
    (
        "transmission_indirect",
        "Transmission indirect",
        "everything else seen through the first hit's glass: Blender's TransInd without the "
        "colour factor",
    ),
    (
        "emission",
        "Emission",
        "what the first hit emits (emissive and unlit materials): Blender's Emit",
    ),
    ("background", "Background", "the environment where the camera ray hit nothing: Blender's Env"),
)


def _lobe_channel(name: str, label: str, help_text: str) -> Channel:
    return Channel(
        name,
        f"the radiance of the `{name}` lobe: a sum over samples, float64",
        Accumulate.SUM,
        name,
        (Array(f"{name}_sum", "<f8", 3),),
        (
            Layer(
                name,
                (f"{name}.R", f"{name}.G", f"{name}.B"),
                label,
                f"{help_text}; the lobe rows sum to `rgb`",
            ),
        ),  # fmt: skip
        setting="aovs",
        aov="lobes",
        wire_components=3,
    )


# The template layer of the light_groups row: a job's layout has one per group, named
# light_group.<group> (the PNG layer `light_group` with `group`), whose EXR channels are
# light_group_<group>.R, .G and .B: one level of layer, which Blender's and Nuke's EXR readers
# take as a pass of the image's layer like the others (Blender reads a second dot as a view
# layer of its own).
LIGHT_GROUP_LAYER = "light_group"

# The depth where the first sample's camera ray hit nothing, as Blender's Depth pass has it.
BACKGROUND_DEPTH = 1e10

CHANNELS: tuple[Channel, ...] = (
    Channel(
        "rgb",
        "the radiance: a sum over samples, float64",
        Accumulate.SUM,
        "rgb_sum",
        (Array("rgb_sum", "<f8", 3),),
        (Layer("rgb", ("R", "G", "B"), "Image", "mean radiance: the unbiased estimate"),),
        wire_components=3,
    ),
    Channel(
        "luminance",
        "the luminance statistics of the radiance, float64",
        Accumulate.MOMENTS,
        "luminance_m2",
        (Array("lum_mean", "<f8"), Array("m2_within", "<f8"), Array("m2_between", "<f8")),
        (
            Layer(
                "variance",
                ("variance.Y",),
                "Std. error",
                "estimated variance of the mean luminance (inf where unknown; the PNG and "
                "the dashboard show its square root, the standard error)",
                Display.GREY,
            ),
            Layer(
                "spp",
                ("spp",),
                "Samples / pixel",
                "samples merged per pixel",
                Display.GREY,
                reads=(),
            ),
            Layer(
                "error",
                ("error",),
                "Relative error",
                "per-pixel relative error: sqrt(variance.Y) / max(Y - sqrt(variance.Y), 0.01), "
                "Y the mean luminance",
                Display.GREY,
            ),
        ),
        wire_components=1,
    ),
    Channel(
        "albedo",
        "the first hit's base colour, a sum over each pixel's first 16 samples, float32",
        Accumulate.SUM,
        "albedo_sum",
        (Array("albedo_sum", "<f4", 3),),
        (
            Layer(
                "albedo",
                ("albedo.R", "albedo.G", "albedo.B"),
                "Albedo",
                "mean first-hit albedo (of the first 16 samples)",
            ),
        ),
        window=AOV_SAMPLES,
        wire_components=3,
    ),
    Channel(
        "normal",
        "the first hit's shading normal in world space, a sum over each pixel's first 16 "
        "samples, float32",
        Accumulate.SUM,
        "normal_sum",
        (Array("normal_sum", "<f4", 3),),
        (
            Layer(
                "normal",
                ("normal.X", "normal.Y", "normal.Z"),
                "Normal",
                "mean first-hit shading normal, world space (of the first 16 samples)",
                Display.SIGNED,
            ),
        ),
        window=AOV_SAMPLES,
        wire_components=3,
    ),
    Channel(
        "coverage",
        "samples whose camera ray hit geometry: a count, float32 (exact to 2^24 samples)",
        Accumulate.COUNT,
        "coverage_sum",
        (Array("coverage_sum", "<f4"),),
        (
            Layer(
                None,
                ("A",),
                "Alpha",
                "alpha: the share of the pixel's samples whose camera ray hit geometry (0 "
                "where only the background or the environment is seen, fractional along "
                "silhouettes), over every sample like the colour; the EXR's alpha channel. The "
                "colour is not premultiplied by it: `R,G,B` are the pixel's full estimate, "
                "background or environment included",
                Display.GREY,
            ),
        ),
        wire_components=1,
    ),
    Channel(
        "depth",
        "the first sample's depth along the camera's viewing axis, float32",
        Accumulate.FIRST,
        "depth",
        (Array("depth", "<f4"),),
        (
            Layer(
                "depth",
                ("depth.Z",),
                "Depth",
                "depth of the first hit of each pixel's first sample: its distance from the "
                "camera along the viewing axis (planar, not along the ray), in scene units, "
                "1e10 where the ray hit nothing; the values of Blender's Depth pass",
                Display.DEPTH,
            ),
        ),
        window=1,
        setting="aovs",
        aov="depth",
        wire_components=1,
    ),
    Channel(
        "position",
        "the first sample's first hit in world space, float32",
        Accumulate.FIRST,
        "position",
        (Array("position", "<f4", 3),),
        (
            Layer(
                "position",
                ("position.X", "position.Y", "position.Z"),
                "Position",
                "world-space position (glTF axes, scene units) of the first hit of each "
                "pixel's first sample, 0 where the ray hit nothing; the values of Blender's "
                "Position pass in glTF's axes (Blender's X, Z, -Y)",
                Display.RANGE,
            ),
        ),
        window=1,
        setting="aovs",
        aov="position",
        wire_components=3,
    ),
    Channel(
        "motion",
        "the first sample's first hit's screen-space motion from the previous and to the next "
        "frame, float32",
        Accumulate.FIRST,
        "motion",
        (Array("motion", "<f4", 4),),
        (
            Layer(
                "motion",
                ("motion.X", "motion.Y", "motion.Z", "motion.W"),
                "Motion",
                "screen-space motion of the surface point of the first hit of each pixel's first "
                "sample, in pixels, y up, as Blender's Vector pass has it: X, Y its position in "
                "the previous frame minus its position now, Z, W its position now minus its "
                "position in the next frame (so its motion to the next frame in image "
                "coordinates, x right and y down, is (-Z, W)); frames are 1 / fps apart, "
                "cameras included; 0 for a still and where the ray hit nothing",
                Display.FLOW,
            ),
        ),
        window=1,
        setting="aovs",
        aov="motion",
        wire_components=4,
    ),
    Channel(
        "instance",
        "the glTF node of the first sample's first hit, plus one (0: none), uint32",
        Accumulate.FIRST,
        "instance",
        (Array("instance_id", "<u4"),),
        (
            Layer(
                "instance",
                ("instance.id",),
                "Instance",
                "instance segmentation: the index in the glTF's `nodes` of the node whose mesh "
                "(or points or lines) the first hit of each pixel's first sample is on, plus "
                "one; 0 where the ray hit nothing. An integer, exact in the EXR's float32 "
                "(indices below 2^24)",
                Display.LABEL,
            ),
        ),
        window=1,
        setting="aovs",
        aov="ids",
        wire_components=1,
        wire_type="<u4",
    ),
    Channel(
        "material",
        "the glTF material of the first sample's first hit, plus one (0: none), uint32",
        Accumulate.FIRST,
        "material",
        (Array("material_id", "<u4"),),
        (
            Layer(
                "material",
                ("material.id",),
                "Material",
                "material segmentation: the index in the glTF's `materials` of the material "
                "the first hit of each pixel's first sample is rendered with (the selected "
                "variant's, KHR_materials_variants), plus one; 0 where the ray hit nothing or "
                "the primitive has no material (glTF's default material). An integer, exact "
                "in the EXR's float32",
                Display.LABEL,
            ),
        ),
        window=1,
        setting="aovs",
        aov="ids",
        wire_components=1,
        wire_type="<u4",
    ),
    Channel(
        "crypto_object",
        "Cryptomatte of the glTF nodes: per pixel the 6 nodes the most samples' first hits were "
        "on, with their counts, as (label, count) pairs, uint32",
        Accumulate.RANKED,
        "crypto_object",
        (Array("crypto_object", "<u4", 2 * CRYPTO_RANKS),),
        (
            Layer(
                "crypto_object",
                _crypto_channels("CryptoObject"),
                "Cryptomatte object",
                "Cryptomatte by glTF node name (CryptoObject): the IDs of the 6 nodes covering "
                "most of the pixel and their coverage (the share of its samples whose camera "
                "ray's first hit is on the node), over every sample",
                Display.MATTE,
            ),
            Layer(
                "crypto_asset",
                _crypto_channels("CryptoAsset"),
                "Cryptomatte asset",
                "Cryptomatte by the name of each node's root node (CryptoAsset): a model's "
                "parts as one matte",
                Display.MATTE,
                reads=("crypto_object",),
            ),
        ),
        setting="aovs",
        aov="cryptomatte",
        wire_components=2 * CRYPTO_RANKS,
        wire_type="<u4",
    ),
    Channel(
        "crypto_material",
        "Cryptomatte of the glTF materials: per pixel the 6 materials the most samples' first "
        "hits had, with their counts, as (label, count) pairs, uint32",
        Accumulate.RANKED,
        "crypto_material",
        (Array("crypto_material", "<u4", 2 * CRYPTO_RANKS),),
        (
            Layer(
                "crypto_material",
                _crypto_channels("CryptoMaterial"),
                "Cryptomatte material",
                "Cryptomatte by glTF material name (CryptoMaterial; the selected variant's "
                "material), over every sample",
                Display.MATTE,
            ),
        ),
        setting="aovs",
        aov="cryptomatte",
        wire_components=2 * CRYPTO_RANKS,
        wire_type="<u4",
    ),
    *(_lobe_channel(*lobe) for lobe in LOBES),
    Channel(
        "light_groups",
        "the radiance of each light group of the job: RGB sums over samples, float64, one "
        "block of three per group",
        Accumulate.SUM,
        "light_groups",
        (Array("light_groups_sum", "<f8", 3),),
        (
            Layer(
                LIGHT_GROUP_LAYER,
                ("light_group_{group}.R", "light_group_{group}.G", "light_group_{group}.B"),
                "Light group",
                "the radiance that came from the lights of one light group (a "
                "KHR_lights_punctual light or emissive node, by its name or its "
                "`extras.light_group`, or the environment), one layer per group; the groups "
                "sum to `rgb`",
            ),
        ),
        setting="aovs",
        aov="light_groups",
        wire_components=3,
        per_group=True,
    ),
    Channel(
        "adaptive",
        "per-pixel adaptive sampling's state (settings.adaptive pixel): each pixel's merged "
        "samples, float32 (exact to 2^24), and the last batch it renders, int32 (2^31 - 1 while "
        "it has not stopped); the `spp` layer reads the samples",
        Accumulate.SERVER,
        "",
        (Array("pixel_spp", "<f4"), Array("stop_batch", "<i4")),
        (),
        setting="adaptive",
    ),
    Channel(
        "denoised",
        "Open Image Denoise of the radiance with the albedo and normal as guides, at output",
        Accumulate.DERIVED,
        "",
        (),
        (
            Layer(
                "denoised",
                ("denoised.R", "denoised.G", "denoised.B"),
                "Denoised",
                "Intel Open Image Denoise (RT filter, HDR, high quality) of `rgb` guided by "
                "`albedo` and `normal`",
                reads=("rgb_sum", "albedo_sum", "normal_sum"),
            ),
        ),
        setting="denoise",
    ),
)

BY_NAME = {c.name: c for c in CHANNELS}


def _check_table() -> None:
    names = [c.name for c in CHANNELS]
    arrays = [a.name for c in CHANNELS for a in c.store]
    exr = [e for c in CHANNELS for layer in c.layers for e in layer.exr]
    layers = [layer.name for c in CHANNELS for layer in c.layers if layer.name]
    for what, values in (("row", names), ("array", arrays), ("EXR channel", exr),
                         ("layer", layers)):  # fmt: skip
        dupes = {v for v in values if values.count(v) > 1}
        if dupes:
            raise AssertionError(f"channel table: {what} named twice: {sorted(dupes)}")
    for c in CHANNELS:
        # A window ends on a batch boundary of the schedule (a power of two up to 64).
        if c.window and (c.window > 64 or c.window & (c.window - 1)):
            raise AssertionError(f"channel {c.name}: window {c.window} is no batch boundary")
        if (c.accumulate is Accumulate.DERIVED) != (not c.store):
            raise AssertionError(f"channel {c.name}: only derived rows store nothing")
        on_server = c.accumulate in (Accumulate.DERIVED, Accumulate.SERVER)
        if on_server != (not c.wire_components):
            raise AssertionError(f"channel {c.name}: every accumulated row is on the wire")
        if (c.accumulate is Accumulate.FIRST) != (c.window == 1):
            raise AssertionError(f"channel {c.name}: first-sample rows have a window of 1")
        if c.accumulate is Accumulate.RANKED and (c.window or c.wire_type != "<u4"):
            raise AssertionError(f"channel {c.name}: ranked rows are uint32 over every sample")
        if bool(c.aov) != (c.setting == "aovs"):
            raise AssertionError(f"channel {c.name}: a row of `aovs` has its name there")


_check_table()


# ----------------------------------------------------------------------------- the layout
# The names the job setting `aovs` takes, in table order (a name may turn on several rows:
# `ids` the instance and the material rows).
AOV_NAMES = tuple(dict.fromkeys(c.aov for c in CHANNELS if c.aov))
ARRAYS = {a.name: a for c in CHANNELS for a in c.store}  # every array the table knows
WIRE = tuple(c for c in CHANNELS if c.wire_components)  # the rows results can carry


def parse_aovs(value: str) -> tuple[str, ...]:
    """The outputs a job's `aovs` setting names (a comma list), in table order, each once; a
    ValueError naming an unknown one."""
    names = {n.strip() for n in value.split(",") if n.strip()}
    unknown = sorted(names - set(AOV_NAMES))
    if unknown:
        raise ValueError(f"unknown output {unknown[0]!r}; known: {', '.join(AOV_NAMES)}")
    return tuple(n for n in AOV_NAMES if n in names)


@dataclass(frozen=True)
class Layout:
    """The rows of one job (layout_for): what its accumulators keep, what its results carry,
    what its images hold and what it costs in memory."""

    rows: tuple[Channel, ...]
    # The job's light groups in layer order (settings.light_groups), which a per-group row's
    # blocks follow: () when it has none.
    groups: tuple[str, ...] = ()

    def stored(self, windowed: bool | None = None) -> tuple[Array, ...]:
        """The arrays the server keeps in table order: of every row (None), of rows over every
        sample (False: checkpointed with each checkpoint) or of windowed rows (True)."""
        return tuple(
            a for c in self.rows if windowed is None or bool(c.window) == windowed
            for a in c.store
        )  # fmt: skip

    def array_names(self, windowed: bool | None = None) -> tuple[str, ...]:
        return tuple(a.name for a in self.stored(windowed))

    def bytes_per_pixel(self, windowed: bool | None = None) -> int:
        """Bytes a pixel of the arrays of stored(windowed)."""
        return sum(a.bytes_per_pixel for a in self.stored(windowed))

    def wire_rows_for(self, sample_start: int) -> tuple[Channel, ...]:
        """The rows a result of the batch starting at sample_start carries: those whose window
        holds it (Task.channels)."""
        return tuple(
            c for c in self.rows if c.wire_components and (not c.window or sample_start < c.window)
        )

    def exr_channels(self) -> tuple[str, ...]:
        """The EXR's channels in order: every row's layers' channels in table order."""
        return tuple(e for c in self.rows for layer in c.layers for e in layer.exr)

    def layers(self) -> dict[str, Layer]:
        """The named layers in table order."""
        return {layer.name: layer for c in self.rows for layer in c.layers if layer.name}

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.rows)


def group_layer(group: str) -> str:
    """The layer of one light group in a job's layout (its EXR channels: light_group_<group>.R,
    .G and .B)."""
    return f"{LIGHT_GROUP_LAYER}.{group}"


def _resolve(c: Channel, groups: tuple[str, ...]) -> Channel:
    """A per-group row for a job's groups: its arrays and wire blocks repeated per group, one
    layer each."""
    if not c.per_group:
        return c
    (template,) = c.layers
    n = len(groups)
    return dataclasses.replace(
        c,
        store=tuple(Array(a.name, a.dtype, a.components * n) for a in c.store),
        layers=tuple(
            dataclasses.replace(
                template,
                name=group_layer(g),
                exr=tuple(e.replace("{group}", g) for e in template.exr),
                label=f"{template.label} {g}",
            )
            for g in groups
        ),
        wire_components=c.wire_components * n,
    )


@functools.cache
def _layout(
    aovs: tuple[str, ...], denoise: bool, groups: tuple[str, ...], pixels: bool = False
) -> Layout:
    rows = tuple(
        _resolve(c, groups) for c in CHANNELS
        if not c.setting or (c.setting == "denoise" and denoise)
        or (c.setting == "adaptive" and pixels) or c.aov in aovs
    )  # fmt: skip
    on = any(c.per_group for c in rows)
    return Layout(rows, groups if on else ())


def layout_for(
    aovs: str | tuple[str, ...] = (),
    denoise: bool = False,
    groups: tuple[str, ...] = (),
    pixel_adaptive: bool = False,
) -> Layout:
    """The layout of a job with these settings: the rows always on, and those its `aovs` (a
    comma list or the names), `denoise` and per-pixel adaptive sampling turn on; `groups`: its
    light groups in order (of settings.light_groups; a job with light_groups has at least the
    environment's, which stands in for them while they are not known)."""
    names = parse_aovs(aovs) if isinstance(aovs, str) else parse_aovs(",".join(aovs))
    if "light_groups" in names and not groups:
        groups = (ENVIRONMENT_GROUP,)
    return _layout(names, bool(denoise), tuple(groups), bool(pixel_adaptive))


@functools.lru_cache(maxsize=256)
def group_names(light_groups: str) -> tuple[str, ...]:
    """The light groups of a job's settings.light_groups (domain/light_groups.py), in layer
    order: () for none. Parsed once per value (a job's layout is asked for every task)."""
    return tuple(json.loads(light_groups)) if light_groups else ()


def job_layout(settings) -> Layout:
    """The layout of a job's settings (jobspec.JobSettings)."""
    return layout_for(
        settings.aovs, settings.denoise, group_names(settings.light_groups),
        pixel_adaptive(settings),
    )  # fmt: skip


def pixel_adaptive(settings) -> bool:
    """Whether a job samples adaptively per pixel (settings.adaptive pixel; without a noise
    threshold no pixel stops, but a continue may set one): adaptive pixel or pixel_mse."""
    return settings.adaptive in ("pixel", "pixel_mse")


# The light group of the environment (domain/light_groups.py), always a job's last.
ENVIRONMENT_GROUP = "environment"
# Every row at once (a job with every output on, one light group: the environment).
EVERY = layout_for(AOV_NAMES, True, pixel_adaptive=True)

# Which workers may render a job: a worker says in its Hello the rows it renders
# (workers.proto, Hello.channels), and the scheduler matches them as tags, this prefix and the
# row's name, which user tags (letters, digits, '.', '_', '-') can never be.
CAPABILITY_PREFIX = "channel:"


def capability_tags(rows) -> frozenset[str]:
    """The capability tags of the rows named (or given) beyond those every job has: a worker's,
    from its Hello, or a job's, from its layout (None: every row of the table)."""
    names = [c.name for c in CHANNELS] if rows is None else [getattr(r, "name", r) for r in rows]
    return frozenset(
        CAPABILITY_PREFIX + n for n in names if n in BY_NAME and n not in DEFAULT.names
        and BY_NAME[n].wire_components
    )  # fmt: skip


DEFAULT = layout_for()  # a job that turns nothing on


def stored(windowed: bool | None = None) -> tuple[Array, ...]:
    """DEFAULT.stored(windowed)."""
    return DEFAULT.stored(windowed)


STATS_ARRAYS = DEFAULT.array_names(False)
WINDOWED_ARRAYS = DEFAULT.array_names(True)


def wire_rows_for(sample_start: int) -> tuple[Channel, ...]:
    """DEFAULT.wire_rows_for(sample_start)."""
    return DEFAULT.wire_rows_for(sample_start)


def bytes_per_pixel(windowed: bool | None = None) -> int:
    """DEFAULT.bytes_per_pixel(windowed)."""
    return DEFAULT.bytes_per_pixel(windowed)


def exr_channels(denoise: bool = False) -> tuple[str, ...]:
    """The EXR's channels of a job with nothing but `denoise` turned on."""
    return layout_for((), denoise).exr_channels()


def layers() -> dict[str, Layer]:
    """Every named layer of the table in table order (a job has those of its layout; a
    per-group row's template stands for its groups' layers)."""
    return {layer.name: layer for c in CHANNELS for layer in c.layers if layer.name}


def layer_channel(layer: str) -> Channel:
    """The row a layer belongs to (a light group's layer: the template row's)."""
    if layer.startswith(LIGHT_GROUP_LAYER + "."):
        layer = LIGHT_GROUP_LAYER
    for c in CHANNELS:
        if any(x.name == layer for x in c.layers):
            return c
    raise KeyError(layer)


def layer_arrays(layer: str) -> tuple[str, ...]:
    """The arrays an image of a layer reads."""
    row = layer_channel(layer)
    reads = row.layers[0].reads if row.per_group else layers()[layer].reads
    return tuple(a.name for a in row.store) if reads is None else reads


def layers_markdown() -> str:
    """The outputs table of docs/usage.md."""
    lines = [
        "| layer | EXR channels | what it holds | turned on by |",
        "|---|---|---|---|",
    ]
    for c in CHANNELS:
        for layer in c.layers:
            name = f"`{layer.name}`" if layer.name else "(EXR only)"
            exr = ", ".join(f"`{e}`" for e in layer.exr)
            if len(layer.exr) > 4:  # Cryptomatte's 12: the layers' names
                levels = dict.fromkeys(e.split(".")[0] for e in layer.exr)
                exr = ", ".join(f"`{n}.R/G/B/A`" for n in levels)
            on = f"`{c.setting}`" if c.setting else "always"
            if c.aov:
                on = f"`aovs` with `{c.aov}`"
            lines.append(f"| {name} | {exr} | {layer.help} | {on} |")
    return "\n".join(lines) + "\n"


def cpp_header() -> str:
    """worker/src/render/channel_table.h: the rows a worker renders, for its accumulation and
    its results (`make channels`; test_channel_table fails while it is stale)."""
    rows = WIRE
    ident = {c.name: "".join(p.capitalize() for p in c.name.split("_")) for c in rows}
    types = {"<f4": "F32", "<f8": "F64", "<u4": "U32"}
    lines = [
        "// The channel table's rows a worker renders (server/renderfarm/domain/channels.py):",
        "// generated by `make channels` (scripts/channel_table.py); do not edit.",
        "#pragma once",
        "",
        "#include <cstdint>",
        "",
        "namespace rf::channels {",
        "",
        f"constexpr uint32_t kTableVersion = {TABLE_VERSION};",
        "",
        "// A row, by its place in the table.",
        "enum class Id : uint8_t {",
        *(f"  {ident[c.name]} = {i}," for i, c in enumerate(rows)),
        "};",
        f"constexpr uint32_t kCount = {len(rows)};",
        "",
        "// The type of a row's values in a result (workers.proto, ValueType).",
        "enum class Type : uint8_t { F32 = 1, F64 = 2, U32 = 3 };",
        "",
        "struct Spec {",
        "  Id id;",
        "  const char* name;       // ChannelBlock.name, Task.channels",
        "  uint32_t components;    // values per pixel",
        "  Type type;",
        "  uint32_t window;        // 0: every sample; else a pixel's first `window` samples",
        "  // Ranked ID coverage (Cryptomatte): components / 2 (label, count) pairs of uint32, the",
        "  // labels the most samples had with their counts, by count descending then label",
        "  bool ranked;",
        "  // One block of `components` per light group of the task (settings.light_groups): the",
        "  // result carries components x the group count a pixel",
        "  bool per_group;",
        "};",
        "",
        "constexpr Spec kSpecs[kCount] = {",
        *(
            f'    {{Id::{ident[c.name]}, "{c.name}", {c.wire_components}, '
            f"Type::{types[c.wire_type]}, {c.window}, "
            f"{'true' if c.accumulate is Accumulate.RANKED else 'false'}, "
            f"{'true' if c.per_group else 'false'}}},"
            for c in rows
        ),
        "};",
        "",
        "}  // namespace rf::channels",
        "",
    ]
    return "\n".join(lines)


# ------------------------------------------------------------------------ checkpoint blobs
# A blob: MAGIC, then u16 TABLE_VERSION, u16 array count, u32 pixels, then per array u8 name
# length, the name (ASCII), u8 dtype code, u16 components; then the arrays back to back,
# little-endian, in the order listed. MAGIC reads as a NaN in float32 and in float64, and a
# blob from before the header begins with a finite value (results with NaN or inf are refused,
# scheduler.py), so the two can never be confused.
MAGIC = bytes.fromhex("0000c07f5246f87f")
_DTYPES = {"<f4": 1, "<f8": 2, "<u4": 3, "<i4": 4}
_DTYPE_OF = {v: k for k, v in _DTYPES.items()}


def blob_header(arrays: tuple[Array, ...], pixels: int) -> bytes:
    out = bytearray(MAGIC)
    out += struct.pack("<HHI", TABLE_VERSION, len(arrays), pixels)
    for a in arrays:
        name = a.name.encode("ascii")
        out += struct.pack("<B", len(name)) + name + struct.pack("<BH", _DTYPES[a.dtype],
                                                                 a.components)  # fmt: skip
    return bytes(out)


def has_header(data: bytes) -> bool:
    return bytes(data[: len(MAGIC)]) == MAGIC


def read_header(data: bytes, what: str) -> tuple[int, list[Array], int, int]:
    """(table version, arrays, pixels, offset of the payload) of a blob with a header; a
    ValueError naming `what` for a malformed one."""
    try:
        offset = len(MAGIC)
        version, count, pixels = struct.unpack_from("<HHI", data, offset)
        offset += 8
        arrays = []
        for _ in range(count):
            (length,) = struct.unpack_from("<B", data, offset)
            name = bytes(data[offset + 1 : offset + 1 + length]).decode("ascii")
            offset += 1 + length
            code, components = struct.unpack_from("<BH", data, offset)
            offset += 3
            if code not in _DTYPE_OF:
                raise ValueError(f"array {name}: unknown type {code}")
            arrays.append(Array(name, _DTYPE_OF[code], components))
    except (struct.error, UnicodeDecodeError) as e:
        raise ValueError(f"checkpoint {what}: malformed header ({e})") from None
    if version > TABLE_VERSION:
        raise ValueError(
            f"checkpoint {what}: channel table version {version} is newer than this server's "
            f"({TABLE_VERSION}); run a server as new as the one that wrote it"
        )
    return version, arrays, pixels, offset

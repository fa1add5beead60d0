"""UsdPreviewSurface to glTF metallic-roughness PBR (with KHR_materials_clearcoat, _ior,
_specular, _emissive_strength and KHR_texture_transform).

How each input maps (docs/scenes.md, "USD scenes", says the same for users):
- diffuseColor -> baseColorFactor / baseColorTexture (rgb); opacity -> its alpha: opacity is
  coverage, not transmission (a refracting glass is not what UsdPreviewSurface's opacity means
  in Storm, Karma or Blender's importer). opacityThreshold > 0 -> alphaMode MASK with that
  cutoff; opacity < 1 or an opacity texture without a threshold -> BLEND; else OPAQUE.
- metallic workflow: metallic, roughness -> metallicFactor, roughnessFactor; textures packed into
  one metallicRoughnessTexture (G roughness, B metallic) when they are separate files.
- specular workflow (useSpecularWorkflow = 1): specularColor is the reflectance at normal
  incidence (F0; white at grazing angles): metallic 0, the diffuseColor as base colour, and
  KHR_materials_specular's specularColorFactor = specularColor / F0(ior), so that the
  extension's F0 = min(F0(ior) x specularColorFactor, 1) is the specularColor (a metal's
  bright specularColor included: its diffuseColor is usually black). A textured specularColor
  is warned and its fallback used.
- clearcoat, clearcoatRoughness -> KHR_materials_clearcoat; ior -> KHR_materials_ior (it also sets
  the dielectric F0 as in UsdPreviewSurface's metallic workflow); emissiveColor ->
  emissiveFactor, with KHR_materials_emissive_strength above 1; normal (a UsdUVTexture with scale
  2 and bias -1, as the UsdPreviewSurface specification asks) -> normalTexture; another scale
  and bias (a flipped green channel) is re-encoded into the texels (2t' - 1 = t scale + bias).
- UsdUVTexture: wrapS/wrapT -> sampler (black -> clamp, warned), scale -> the factor, st from a
  UsdPrimvarReader_float2 (its varname picks the mesh's TEXCOORD_n) through an optional
  UsdTransform2d -> KHR_texture_transform (with the v flip between USD's st and glTF's uv).
- occlusion is dropped silently (the path tracer computes occlusion); displacement is warned.

It stays one module: every input above is read through the same shader-graph walk (the
connected UsdUVTexture, its primvar reader and transform) and packed into one material's
textures, which splitting by input would only pass around.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import SceneError
from .gltf_writer import GltfWriter
from .usd_assets import backslashed_path, is_udim, packaged_copy, read_inside

WRAP = {"repeat": 10497, "mirror": 33648, "clamp": 33071, "black": 33071, "useMetadata": 10497}
DIRECT_IMAGES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


@dataclass
class TextureRef:
    """One UsdUVTexture output read by a UsdPreviewSurface input."""

    file: str  # resolved path inside the upload
    channels: str  # "rgb", "r", "g", "b" or "a"
    uv: str  # the primvar name (varname) giving st
    transform: tuple[float, float, float, float, float] | None  # sx, sy, rot_deg, tx, ty
    wrap: tuple[int, int]
    scale: tuple[float, float, float, float]
    bias: tuple[float, float, float, float]
    shader: str  # the UsdUVTexture prim path, for messages
    color_space: str
    # A normal map's (scale, bias) per channel other than glTF's 2t - 1: the texels are
    # re-encoded so that 2t' - 1 = t x scale + bias.
    remap: tuple[tuple[float, ...], tuple[float, ...]] | None = None


@dataclass
class MaterialResult:
    index: int
    uv_sets: list[str] = field(default_factory=list)  # TEXCOORD_n is uv_sets[n]
    # diffuseColor read from a primvar (a UsdPrimvarReader): its name and the reader's
    # fallback; the mesh carries it as COLOR_0, which glTF multiplies into the base colour.
    color_primvar: str | None = None
    color_fallback: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _vec(value: Any, n: int) -> tuple[float, ...]:
    if value is None:
        return (0.0,) * n
    if isinstance(value, (int, float)):
        return (float(value),) * n
    return tuple(float(v) for v in list(value)[:n])


def _source(inp):
    """("value", v) or ("output", shader prim, output name) for a shader input, following
    connections through material and node-graph interface inputs."""
    from pxr import UsdShade

    attrs = inp.GetValueProducingAttributes(shaderOutputsOnly=False)
    if not attrs:
        return ("value", inp.Get())
    attr = attrs[0]
    kind, name = UsdShade.Utils.GetBaseNameAndType(attr.GetName())
    if name == UsdShade.AttributeType.Output:
        return ("output", attr.GetPrim(), kind)
    return ("value", attr.Get())


def _shader_id(prim) -> str:
    from pxr import UsdShade

    return str(UsdShade.Shader(prim).GetIdAttr().Get() or "")


def _input_value(shader_prim, name: str, default: Any) -> Any:
    from pxr import UsdShade

    inp = UsdShade.Shader(shader_prim).GetInput(name)
    if not inp:
        return default
    kind, *rest = _source(inp)
    if kind == "value":
        return default if rest[0] is None else rest[0]
    return default


class MaterialConverter:
    """Converts each bound UsdShade.Material once; warnings go to `warn(prim path, text)`."""

    def __init__(self, writer: GltfWriter, root: Path, work: Path, warn):
        self.writer = writer
        self.root = root
        self.work = work
        self.readable = (root, work / "packaged")  # the upload, and packaged_copy's copies
        self.warn = warn
        self.cache: dict[tuple[str, bool], MaterialResult] = {}
        self.images: dict[tuple, int] = {}
        self.samplers: dict[tuple[int, int], int] = {}

    # ---------------------------------------------------------------- textures
    def _texture_ref(self, prim, output: str, where: str) -> TextureRef | None:
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        ident = _shader_id(prim)
        path = str(prim.GetPath())
        if ident != "UsdUVTexture":
            self.warn(path, f"shader {ident or '(no id)'} feeding {where} is not a UsdUVTexture")
            return None
        file_input = shader.GetInput("file")
        asset = _input_value(prim, "file", None)
        if asset is None or not getattr(asset, "path", ""):
            self.warn(path, "UsdUVTexture without inputs:file: its fallback is used")
            return None
        if is_udim(asset.path):
            self.warn(path, "UDIM texture sets are not supported: the texture's fallback is used")
            return None
        resolved = asset.resolvedPath
        if not resolved and "\\" in asset.path:  # Windows separators, which USD keeps as written
            resolved = backslashed_path(file_input, asset.path, self.root, f"{path}.inputs:file")
        if not resolved:
            raise SceneError(
                f"{path}.inputs:file: the texture {asset.path!r} is not a file of the upload",
                f"scene:{path}.inputs:file",
            )
        # A texture inside a .usdz of the upload: its entry copied out (checked) to be read.
        resolved = packaged_copy(resolved, self.root, self.work, f"{path}.inputs:file")
        del file_input
        channels = {"rgb": "rgb", "rgba": "rgb", "r": "r", "g": "g", "b": "b", "a": "a"}.get(output)
        if channels is None:
            self.warn(path, f"texture output {output} is not read; its fallback is used")
            return None
        uv, transform = "st", None
        st = shader.GetInput("st")
        if st:
            kind, *rest = _source(st)
            if kind == "output":
                node = rest[0]
                if _shader_id(node) == "UsdTransform2d":
                    transform = (
                        *_vec(_input_value(node, "scale", (1.0, 1.0)), 2),
                        float(_input_value(node, "rotation", 0.0)),
                        *_vec(_input_value(node, "translation", (0.0, 0.0)), 2),
                    )
                    inner = UsdShade.Shader(node).GetInput("in")
                    kind, *rest = _source(inner) if inner else ("value", None)
                    node = rest[0] if kind == "output" else None
                if node is not None and _shader_id(node).startswith("UsdPrimvarReader"):
                    uv = str(_input_value(node, "varname", "st") or "st")
                elif node is not None:
                    self.warn(path, f"st comes from {node.GetPath()}, not a primvar reader")
        wrap = tuple(
            WRAP.get(str(_input_value(prim, k, "useMetadata")), 10497) for k in ("wrapS", "wrapT")
        )
        if "black" in (str(_input_value(prim, "wrapS", "")), str(_input_value(prim, "wrapT", ""))):
            self.warn(path, "wrap mode black is rendered as clamp")
        return TextureRef(
            file=resolved,
            channels=channels,
            uv=uv,
            transform=transform,
            wrap=wrap,  # type: ignore[arg-type]
            scale=_vec(_input_value(prim, "scale", (1, 1, 1, 1)), 4),  # type: ignore[arg-type]
            bias=_vec(_input_value(prim, "bias", (0, 0, 0, 0)), 4),  # type: ignore[arg-type]
            shader=path,
            color_space=str(_input_value(prim, "sourceColorSpace", "auto")),
        )

    def _image_bytes(
        self, sources: list[TextureRef | None], layout: str, srgb: bool
    ) -> tuple[bytes, str]:
        """A PNG/JPEG for the texture: the file itself when it already has the layout, else
        channels gathered (and resized to the largest) with OpenImageIO into a new PNG.
        `layout` is "rgb", "rgba" or "rgb0" (G, B packed, R unused)."""
        first = next(s for s in sources if s is not None)
        files = {s.file for s in sources if s is not None}
        suffix = Path(first.file).suffix.lower()
        transfer = any(s is not None and _transfer(s, srgb) for s in sources)
        if (
            len(files) == 1
            and suffix in DIRECT_IMAGES
            and not transfer
            and self._direct(sources, layout)
        ):
            return read_inside(first.file, self.readable, first.shader), DIRECT_IMAGES[suffix]
        return self._pack(sources, layout, srgb), "image/png"

    def _direct(self, sources: list[TextureRef | None], layout: str) -> bool:
        import OpenImageIO as oiio

        first = next(s for s in sources if s is not None)
        if any(s is not None and s.remap is not None for s in sources):
            return False
        spec = oiio.ImageInput.open(first.file)
        if spec is None:
            return False
        nchannels = spec.spec().nchannels
        spec.close()
        if layout == "rgb":
            return sources[0] is not None and sources[0].channels == "rgb" and nchannels in (1, 3)
        if layout == "rgba":
            return (
                sources[0] is not None
                and sources[0].channels == "rgb"
                and sources[1] is not None
                and sources[1].channels == "a"
                and nchannels == 4
            )
        # metallic-roughness: roughness from G and metallic from B of one file
        rough, metal = sources[1], sources[2]
        return (
            len(sources) == 3
            and sources[0] is None
            and rough is not None
            and metal is not None
            and (rough.channels, metal.channels) == ("g", "b")
        )

    def _pack(self, sources: list[TextureRef | None], layout: str, srgb: bool) -> bytes:
        """A new PNG: "rgb" one source's colour (a single channel repeated), "rgba" source 0's
        colour and source 1's channel as alpha, "rgb0" one channel of each source in R, G, B.
        A missing source is 1 (the glTF factor then gives the value)."""
        import OpenImageIO as oiio

        bufs = {}
        for s in sources:
            if s is not None and s.file not in bufs:
                read_inside(s.file, self.readable, s.shader)  # the check; OpenImageIO reads it
                buf = oiio.ImageBuf(s.file)
                if buf.has_error or not buf.initialized:
                    raise SceneError(
                        f"{s.shader}.inputs:file: {Path(s.file).name} cannot be read as an image",
                        f"scene:{s.shader}.inputs:file",
                    )
                pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
                if pixels.ndim == 2:
                    pixels = pixels[:, :, None]
                bufs[s.file] = pixels
        height = max(p.shape[0] for p in bufs.values())
        width = max(p.shape[1] for p in bufs.values())

        def channel_values(s: TextureRef) -> np.ndarray:
            pixels = _resize(bufs[s.file], height, width)
            n = pixels.shape[2]
            if s.channels == "rgb":
                values = pixels[:, :, [0, 0, 0]] if n < 3 else pixels[:, :, :3]
                if srgb and Path(s.file).suffix.lower() in (".exr", ".hdr"):
                    values = _to_srgb(values)
                values = _apply_transfer(values, _transfer(s, srgb))
                if s.remap is not None:
                    scale, bias = (np.array(v, np.float32) for v in s.remap)
                    values = np.clip((values * scale + bias + 1.0) / 2.0, 0.0, 1.0)
                return values
            pick = {"r": 0, "g": 1, "b": 2, "a": 3}[s.channels]
            if pick >= n:  # a grey image's only channel, or no alpha: opaque
                if s.channels == "a":  # no alpha channel: opaque, as UsdUVTexture reads it
                    return np.ones((height, width, 1), np.float32)
                return _apply_transfer(pixels[:, :, :1], _transfer(s, srgb))  # grey's one channel
            if s.channels == "a":  # alpha is linear in every colour space
                return pixels[:, :, 3:4]
            return _apply_transfer(pixels[:, :, pick : pick + 1], _transfer(s, srgb))

        if layout == "rgb":
            out = channel_values(sources[0])  # type: ignore[arg-type]
            if out.shape[2] == 1:
                out = np.repeat(out, 3, axis=2)
        else:
            out = np.ones((height, width, 4 if layout == "rgba" else 3), np.float32)
            if layout == "rgba":
                if sources[0] is not None:
                    out[:, :, :3] = channel_values(sources[0])
                if sources[1] is not None:
                    out[:, :, 3:4] = channel_values(sources[1])[:, :, :1]
            else:
                for i, s in enumerate(sources):
                    if s is not None:
                        out[:, :, i : i + 1] = channel_values(s)[:, :, :1]
        return _png(out, self.work)

    def texture(
        self, sources: list[TextureRef | None], layout: str, srgb: bool, uv_sets: list[str]
    ) -> dict[str, Any] | None:
        """A glTF textureInfo for the sources (their first gives uv set, wrap and transform)."""
        present = [s for s in sources if s is not None]
        if not present:
            return None
        first = present[0]
        for other in present[1:]:
            if (other.uv, other.transform, other.wrap) != (first.uv, first.transform, first.wrap):
                self.warn(
                    other.shader,
                    f"packed with {first.shader} into one glTF texture: it takes that one's "
                    "st, transform and wrap",
                )
        key = (
            tuple((s.file, s.channels, s.remap, s.color_space) if s else None for s in sources),
            layout,
            srgb,
        )
        image = self.images.get(key)
        if image is None:
            data, mime = self._image_bytes(sources, layout, srgb)
            image = self.writer.image(data, mime, os.path.basename(first.file))
            self.images[key] = image
        sampler = self.samplers.get(first.wrap)
        if sampler is None:
            sampler = self.writer.add(
                "samplers",
                {
                    "wrapS": first.wrap[0],
                    "wrapT": first.wrap[1],
                    "magFilter": 9729,
                    "minFilter": 9729,
                },
            )
            self.samplers[first.wrap] = sampler
        index = self.writer.add("textures", {"source": image, "sampler": sampler})
        if first.uv not in uv_sets:
            uv_sets.append(first.uv)
        info: dict[str, Any] = {"index": index}
        tex_coord = uv_sets.index(first.uv)
        if tex_coord:
            info["texCoord"] = tex_coord
        if first.transform is not None:
            transform = texture_transform(*first.transform)
            if transform:
                info.setdefault("extensions", {})["KHR_texture_transform"] = transform
                self.writer.use_extension("KHR_texture_transform")
        return info

    # ---------------------------------------------------------------- materials
    def convert(self, material, double_sided: bool) -> MaterialResult | None:
        """The glTF material of a UsdShade.Material (None: no UsdPreviewSurface; warned)."""
        key = (str(material.GetPath()), double_sided)
        if key in self.cache:
            return self.cache[key]
        result = self._convert(material, double_sided)
        self.cache[key] = result  # type: ignore[assignment]
        return result

    def _convert(self, material, double_sided: bool) -> MaterialResult | None:
        path = str(material.GetPath())
        surface = material.ComputeSurfaceSource()
        shader = surface[0] if surface else None
        if not shader or _shader_id(shader.GetPrim()) != "UsdPreviewSurface":
            kinds = [o.GetBaseName() for o in material.GetOutputs()]
            self.warn(
                path,
                f"no UsdPreviewSurface (outputs: {', '.join(kinds) or 'none'}); MaterialX, MDL "
                "and other surfaces are not converted: a grey default is used",
            )
            return None
        prim = shader.GetPrim()
        sp = str(prim.GetPath())
        uv_sets: list[str] = []

        def read(name: str, default: Any):
            """(constant value, TextureRef or None)."""
            inp = shader.GetInput(name)
            if not inp:
                return default, None
            kind, *rest = _source(inp)
            if kind == "value":
                return (default if rest[0] is None else rest[0]), None
            src_prim, output = rest
            ref = self._texture_ref(src_prim, output, f"{sp}.inputs:{name}")
            if ref is None:  # unread: the UsdUVTexture's fallback, as the spec says
                return _fallback(src_prim, output, default), None
            return default, ref

        color_primvar, color_fallback = self._color_primvar(shader, sp)
        if color_primvar is not None:
            diffuse, diffuse_tex = (1.0, 1.0, 1.0), None
        else:
            diffuse, diffuse_tex = read("diffuseColor", (0.18, 0.18, 0.18))
        opacity, opacity_tex = read("opacity", 1.0)
        threshold, _ = read("opacityThreshold", 0.0)
        emissive, emissive_tex = read("emissiveColor", (0.0, 0.0, 0.0))
        specular_workflow, _ = read("useSpecularWorkflow", 0)
        specular, specular_tex = read("specularColor", (0.0, 0.0, 0.0))
        metallic, metallic_tex = read("metallic", 0.0)
        roughness, roughness_tex = read("roughness", 0.5)
        clearcoat, clearcoat_tex = read("clearcoat", 0.0)
        coat_rough, coat_rough_tex = read("clearcoatRoughness", 0.01)
        ior, ior_tex = read("ior", 1.5)
        _normal, normal_tex = read("normal", (0.0, 0.0, 1.0))
        _disp, disp_tex = read("displacement", 0.0)
        displacement_value = _input_value(prim, "displacement", 0.0)
        if disp_tex is not None or float(displacement_value or 0.0) != 0.0:
            self.warn(sp, "displacement is not rendered")
        if ior_tex is not None:
            self.warn(sp, "a textured ior is not supported; its fallback 1.5 is used")

        gltf: dict[str, Any] = {"name": path}
        pbr: dict[str, Any] = {}
        ext: dict[str, Any] = {}
        base = list(_vec(diffuse, 3))
        alpha = float(opacity)
        if diffuse_tex is not None:
            base = list(diffuse_tex.scale[:3])
            self._bias_warning(diffuse_tex)
        if opacity_tex is not None:
            alpha = opacity_tex.scale[_chan(opacity_tex)]
        ior = float(ior)
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 if ior > 0 else 0.04

        if int(specular_workflow):
            spec = _vec(specular, 3)
            if specular_tex is not None:
                self.warn(sp, "a textured specularColor is not supported: its fallback is used")
            pbr["metallicFactor"] = 0.0
            if f0 > 0.0:
                colour = [max(0.0, c) / f0 for c in spec]
                if any(abs(c - 1.0) > 1e-6 for c in colour):
                    ext["KHR_materials_specular"] = {"specularColorFactor": colour}
            else:  # ior 1: no dielectric reflection whatever the colour
                ext["KHR_materials_specular"] = {"specularFactor": 0.0}
            pbr["roughnessFactor"] = float(roughness)
            metallic_tex = None
        else:
            pbr["metallicFactor"] = float(metallic)
            pbr["roughnessFactor"] = float(roughness)
            if metallic_tex is not None:
                pbr["metallicFactor"] = metallic_tex.scale[_chan(metallic_tex)]
            if roughness_tex is not None:
                pbr["roughnessFactor"] = roughness_tex.scale[_chan(roughness_tex)]
        pbr["baseColorFactor"] = [*base, alpha]

        info = (
            self.texture(
                [diffuse_tex, opacity_tex], "rgba" if opacity_tex else "rgb", True, uv_sets
            )
            if diffuse_tex or opacity_tex
            else None
        )
        if info is not None:
            pbr["baseColorTexture"] = info
        if metallic_tex or roughness_tex:
            if metallic_tex:
                self._bias_warning(metallic_tex)
            if roughness_tex:
                self._bias_warning(roughness_tex)
            pbr["metallicRoughnessTexture"] = self.texture(
                [None, roughness_tex, metallic_tex], "rgb0", False, uv_sets
            )
        gltf["pbrMetallicRoughness"] = pbr

        if normal_tex is not None:
            if any(abs(s - 2.0) > 1e-3 for s in normal_tex.scale[:3]) or any(
                abs(b + 1.0) > 1e-3 for b in normal_tex.bias[:3]
            ):
                # Another encoding (a flipped green channel, an unbiased z): the texels are
                # re-encoded so that glTF's 2t' - 1 is USD's t x scale + bias.
                normal_tex = replace(normal_tex, remap=(normal_tex.scale[:3], normal_tex.bias[:3]))
            gltf["normalTexture"] = self.texture([normal_tex], "rgb", False, uv_sets)

        emit = list(_vec(emissive, 3))
        if emissive_tex is not None:
            emit = list(emissive_tex.scale[:3])
            gltf["emissiveTexture"] = self.texture([emissive_tex], "rgb", True, uv_sets)
        _set_emission(gltf, emit, self.writer)

        coat = (
            float(clearcoat) if clearcoat_tex is None else clearcoat_tex.scale[_chan(clearcoat_tex)]
        )
        if coat > 0.0 or clearcoat_tex is not None:
            cc: dict[str, Any] = {"clearcoatFactor": coat}
            cc["clearcoatRoughnessFactor"] = (
                float(coat_rough)
                if coat_rough_tex is None
                else coat_rough_tex.scale[_chan(coat_rough_tex)]
            )
            if clearcoat_tex is not None:
                cc["clearcoatTexture"] = self.texture(
                    [clearcoat_tex, None, None], "rgb0", False, uv_sets
                )
            if coat_rough_tex is not None:
                cc["clearcoatRoughnessTexture"] = self.texture(
                    [None, coat_rough_tex, None], "rgb0", False, uv_sets
                )
            ext["KHR_materials_clearcoat"] = cc
        if abs(ior - 1.5) > 1e-6:
            ext["KHR_materials_ior"] = {"ior": ior}

        threshold = float(threshold)
        if threshold > 0.0:
            gltf["alphaMode"] = "MASK"
            gltf["alphaCutoff"] = threshold
        elif alpha < 1.0 or opacity_tex is not None:
            gltf["alphaMode"] = "BLEND"
        if double_sided:
            gltf["doubleSided"] = True
        for name, value in ext.items():
            gltf.setdefault("extensions", {})[name] = value
            self.writer.use_extension(name)
        index = self.writer.add("materials", gltf)
        return MaterialResult(index=index, uv_sets=uv_sets, color_primvar=color_primvar,
                              color_fallback=color_fallback)  # fmt: skip

    def _color_primvar(self, shader, where: str) -> tuple[str | None, tuple[float, ...]]:
        """(the primvar a UsdPrimvarReader_float3 (or _float4) feeding diffuseColor reads, the
        reader's fallback) or (None, ()) when diffuseColor comes from elsewhere."""
        inp = shader.GetInput("diffuseColor")
        if not inp:
            return None, ()
        kind, *rest = _source(inp)
        if kind != "output":
            return None, ()
        reader = rest[0]
        if _shader_id(reader) not in ("UsdPrimvarReader_float3", "UsdPrimvarReader_float4"):
            return None, ()
        name = str(_input_value(reader, "varname", "") or "")
        if not name:
            self.warn(str(reader.GetPath()), "a primvar reader without varname: its fallback")
        return name or "", _vec(_input_value(reader, "fallback", (0.0, 0.0, 0.0)), 3)

    def _bias_warning(self, ref: TextureRef) -> None:
        if any(abs(b) > 1e-6 for b in ref.bias):
            self.warn(ref.shader, "a texture bias is only supported on normal maps; it is ignored")


def _fallback(texture_prim, output: str, default: Any) -> Any:
    """The value a UsdUVTexture gives when its file cannot be read: its `fallback` input's
    channels for `output` (rgb, r, g, b or a); else `default`."""
    value = _input_value(texture_prim, "fallback", None)
    if value is None:
        return default
    rgba = _vec(value, 4)
    if output in ("rgb", "rgba"):
        return rgba[:3]
    index = {"r": 0, "g": 1, "b": 2, "a": 3}.get(output)
    return default if index is None else rgba[index]


def _chan(ref: TextureRef) -> int:
    return {"rgb": 0, "r": 0, "g": 1, "b": 2, "a": 3}[ref.channels]


def _set_emission(gltf: dict[str, Any], emit: list[float], writer: GltfWriter) -> None:
    """emissiveFactor, and KHR_materials_emissive_strength for a radiance above 1."""
    peak = max(emit)
    if peak <= 0.0:
        return
    if peak <= 1.0:
        gltf["emissiveFactor"] = emit
        return
    gltf["emissiveFactor"] = [c / peak for c in emit]
    gltf.setdefault("extensions", {})["KHR_materials_emissive_strength"] = {
        "emissiveStrength": peak
    }
    writer.use_extension("KHR_materials_emissive_strength")


def texture_transform(
    sx: float, sy: float, rotation_deg: float, tx: float, ty: float
) -> dict[str, Any]:
    """KHR_texture_transform equal to a UsdTransform2d (st' = R(rotation) S st + t, in USD's st
    space, v up, R counter-clockwise) in glTF's uv space, where uv = (s, 1 - t): the affine
    map F A F with F(x, y) = (x, 1 - y), decomposed into the extension's T R S. The
    extension's rotation r turns uv as u' = u cos r + v sin r, v' = -u sin r + v cos r: what
    Khronos' TextureTransformTest asset takes as correct (its arrow on the green marker) and
    the workers do (worker/src/scene/textures_test.cpp), so r is minus the angle of F A F's
    rotation. Empty for the identity."""
    a = math.radians(rotation_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    lin_usd = rot @ np.diag([sx, sy])
    flip = np.diag([1.0, -1.0])
    lin = flip @ lin_usd @ flip
    # offset: M(0) = F(A(F(0))) = F(A((0, 1)))
    q = lin_usd @ np.array([0.0, 1.0]) + np.array([tx, ty])
    offset = np.array([q[0], 1.0 - q[1]])
    theta = math.atan2(lin[1, 0], lin[0, 0])
    scale_x = math.hypot(lin[0, 0], lin[1, 0])
    r_inv = np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])
    s = r_inv @ lin  # diagonal when lin = R S
    scale_y = s[1, 1]
    out: dict[str, Any] = {}
    if abs(offset[0]) > 1e-9 or abs(offset[1]) > 1e-9:
        out["offset"] = [float(offset[0]), float(offset[1])]
    if abs(theta) > 1e-9:
        out["rotation"] = float(-theta)
    if abs(scale_x - 1) > 1e-9 or abs(scale_y - 1) > 1e-9:
        out["scale"] = [float(scale_x), float(scale_y)]
    return out


def _resize(pixels: np.ndarray, height: int, width: int) -> np.ndarray:
    if pixels.shape[:2] == (height, width):
        return pixels
    rows = (np.arange(height) * pixels.shape[0] // height).clip(0, pixels.shape[0] - 1)
    cols = (np.arange(width) * pixels.shape[1] // width).clip(0, pixels.shape[1] - 1)
    return pixels[rows][:, cols]


def _transfer(ref: TextureRef, srgb: bool) -> str | None:
    """What an 8- or 16-bit texture's values need so that glTF reads them as USD does: its
    sourceColorSpace says "sRGB" where glTF reads the slot linearly (roughness, metallic,
    opacity, normal...): "decode"; "raw" where glTF decodes sRGB (base and emissive colour):
    "encode"; None otherwise ("auto" is glTF's own reading)."""
    if Path(ref.file).suffix.lower() in (".exr", ".hdr"):
        return None
    if ref.color_space == "sRGB" and not srgb:
        return "decode"
    if ref.color_space == "raw" and srgb:
        return "encode"
    return None


def _apply_transfer(values: np.ndarray, transfer: str | None) -> np.ndarray:
    if transfer == "decode":
        v = np.clip(values, 0.0, 1.0)
        return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)
    if transfer == "encode":
        return _to_srgb(values).astype(np.float32)
    return values


def _to_srgb(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _png(pixels: np.ndarray, work: Path) -> bytes:
    import tempfile

    import OpenImageIO as oiio

    height, width, channels = pixels.shape
    spec = oiio.ImageSpec(width, height, channels, oiio.UINT8)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(
        oiio.ROI(0, width, 0, height, 0, 1, 0, channels), np.clip(pixels, 0, 1).astype(np.float32)
    )
    fd, name = tempfile.mkstemp(suffix=".png", dir=work)
    os.close(fd)
    try:
        if not buf.write(name, oiio.UINT8):
            raise SceneError(f"a packed texture could not be written: {buf.geterror()}")
        return Path(name).read_bytes()
    finally:
        os.unlink(name)


__all__ = ["MaterialConverter", "MaterialResult", "texture_transform"]

"""What a USD upload may refer to: files of the upload, and nothing else.

Before a stage is composed (which opens every layer it names), every layer of the upload is read
on its own with Sdf, without composition, and every asset path in it is checked: sublayers,
references, payloads, value clips (assetPaths, manifestAssetPath, and templateAssetPath: the
template itself, and each clip it names over the times the same layer authors, derived as USD
derives them, at most MAX_TEMPLATE_CLIPS) and every asset-valued attribute (defaults and time
samples, in variants too). An asset path must be relative, stay inside the upload's directory
after `..` and symbolic links are resolved, name a file that is there, and be no URL, absolute
path, package path (`a.usdz[b.usd]`) or search path outside the upload; a UDIM tile set
(`tex.<UDIM>.png`) is never read (the converter warns and uses the texture's
fallback). A refusal is a SceneError
whose field names the layer's prim and attribute as USD writes a property path
(`scene:/World/Looks/Wood/Texture.inputs:file`). Layers the checked arcs name are checked in
turn, before anything opens them; only then may Usd.Stage.Open compose the stage. A .usdz that
an arc names is checked from inside: every USD layer in it, its asset paths anchored where USD
anchors them, inside the package (`props.usdz[parts/a.usda]` naming `../maps/b.png` reads
`props.usdz[maps/b.png]`), each of which must stay inside the package and name an entry of it.

After composition, and again after the conversion (which opens value clips' layers as it reads
their values), check_used_layers refuses a stage that used any layer that is not a file of the
upload (or an entry of a .usdz that is one): the defence behind the checks above.

A sublayer, reference or payload naming a MaterialX document (`.mtlx`, as the USD Working
Group's assets and Houdini's exports compose their materials) is checked like any asset path,
then dropped from its layer in memory (never opened: usd-core has no MaterialX file format, and
the converter reads UsdPreviewSurface only) and listed in `CheckedLayers.dropped`, which the
converter warns about, one warning an arc. The edited layers stay open in `CheckedLayers.layers`
so that the stage composes them, not the files.

One module although over 500 lines: the checks of layers, of packages and of the composed stage
are one confinement rule, and a reviewer should read where an asset path may lead in one place.

The converter reads texture bytes through `read_inside`, which checks the resolved path again,
so that a path the checks missed can still read nothing outside the upload; a texture inside a
.usdz of the upload is first copied out of the package by `packaged_copy`.
"""

from __future__ import annotations

import hashlib
import math
import os
import posixpath
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from ...errors import SceneError

USD_LAYER_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
MATERIALX_SUFFIX = ".mtlx"
MAX_TEMPLATE_CLIPS = 10_000  # the clips a value clip template may name over its times


@dataclass
class DroppedArc:
    """A composition arc to a MaterialX document, dropped before the stage is composed."""

    where: str  # the prim path (variant selections stripped), or a layer's name for a sublayer
    kind: str  # "reference", "payload" or "sublayer"
    asset: str  # the asset path as written
    variant: str = ""  # "set=selection" when the arc is authored inside a variant


@dataclass
class CheckedLayers:
    files: list[Path]
    dropped: list[DroppedArc] = field(default_factory=list)
    layers: list[Any] = field(default_factory=list, repr=False)  # open Sdf layers, edits kept


_SOURCE_ASSET = re.compile(r"^info:([^:]+:)?sourceAsset$")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*:")


def _field(where: str) -> str:
    return f"scene:{where}"


def check_asset_path(
    path: str, anchor_dir: Path, root: Path, where: str, *, need_file: bool = True
) -> Path | None:
    """The file an asset path names, inside `root`, or SceneError naming `where` (a prim path
    and attribute, or a layer's sublayer). An empty path names nothing (None). Without
    `need_file` the path may name no file (a value clip template's time USD finds no file for:
    None); it must still stay inside `root`."""
    if not path:
        return None
    _check_written(path, where)
    # A '..' may climb to a folder of the upload (layers/shot.usda naming ../maps/wood.png, as
    # packaged assets do), not above it: checked on the path as written, before any symbolic
    # link is resolved (then again on the resolved path, below).
    shown = _shown(path)
    written = os.path.normpath(os.path.join(anchor_dir, path.replace("\\", "/")))
    if not Path(written).is_relative_to(root):
        raise SceneError(
            f"{where}: the asset path {shown!r} climbs out of the upload with '..'; only files "
            "inside the upload are allowed",
            _field(where),
        )
    if is_udim(path):  # a tile set, not a file: never read (the converter warns)
        return None
    target = Path(os.path.realpath(anchor_dir / path.replace("\\", "/")))
    if not target.is_relative_to(root):
        raise SceneError(
            f"{where}: the asset path {shown!r} leads outside the upload", _field(where)
        )
    if not target.is_file():
        if not need_file:
            return None
        hint = (
            "; the layer was uploaded alone: upload it with the files it names as a .zip "
            "bundle (the layer at the bundle's top, its files at the paths it names)"
            if _lone_file(root)
            else ""
        )
        raise SceneError(
            f"{where}: the asset path {shown!r} names no file of the upload{hint}", _field(where)
        )
    return target


def _lone_file(root: Path) -> bool:
    """Whether the upload is one file (a layer uploaded alone, without the files it names)."""
    entries = []
    for entry in root.iterdir():
        entries.append(entry)
        if len(entries) > 1:
            return False
    return len(entries) == 1 and entries[0].is_file()


def _shown(path: str) -> str:
    return path if len(path) <= 200 else path[:200] + "..."


def _check_written(path: str, where: str) -> None:
    """Refuse what no file of the upload can be, whatever the anchor: a NUL, a URL, an absolute
    path, a package path."""
    shown = _shown(path)
    if "\0" in path:
        raise SceneError(f"{where}: the asset path has a NUL character", _field(where))
    if "://" in path or (_SCHEME.match(path) and not re.match(r"^[A-Za-z]:[\\/]", path)):
        raise SceneError(
            f"{where}: the asset path {shown!r} is a URL; only files of the upload can be read",
            _field(where),
        )
    if path.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:[\\/]", path):
        raise SceneError(
            f"{where}: the asset path {shown!r} is absolute; only paths relative to the layer "
            "inside the upload are allowed",
            _field(where),
        )
    if "[" in path or "]" in path:
        raise SceneError(
            f"{where}: the asset path {shown!r} is a package path; upload the package's files "
            "(or the .usdz itself as the scene) instead",
            _field(where),
        )


def is_udim(path: str) -> bool:
    """Whether an asset path names a UDIM tile set (`tex.<UDIM>.png`)."""
    upper = path.upper()
    return "<UDIM>" in upper or "<UVTILE" in upper


def read_inside(path: str, root: Path | tuple[Path, ...], where: str) -> bytes:
    """The bytes of a resolved asset path, which must be a file inside `root` (or one of the
    folders given)."""
    roots = root if isinstance(root, tuple) else (root,)
    target = Path(os.path.realpath(path)) if path else None
    if target is None or not any(target.is_relative_to(r) for r in roots) or not target.is_file():
        raise SceneError(f"{where}: the asset {path!r} is not a file of the upload", _field(where))
    return target.read_bytes()


def backslashed_path(shader_input, path: str, root: Path, where: str) -> str:
    """The file a relative asset path written with Windows separators (`textures\\wood.png`, as
    exporters on Windows write them) names, which USD's resolver on Linux does not find: the path
    anchored at the folder of the layer that authors the value (check_asset_path, which reads
    '\\' as '/'), or "" (a layer inside a package, or nothing authored)."""
    for attr in shader_input.GetValueProducingAttributes() or []:
        for spec in attr.GetPropertyStack():
            if not (spec.HasDefaultValue() or spec.layer.ListTimeSamplesForPath(spec.path)):
                continue
            real = spec.layer.realPath
            if not real or "[" in real:
                return ""
            target = check_asset_path(path, Path(os.path.realpath(real)).parent, root, where)
            return "" if target is None else str(target)
    return ""


def packaged_copy(resolved: str, root: Path, work: Path, where: str) -> str:
    """A resolved asset path as a file the converter can read: itself, or for a file inside a
    .usdz of the upload (`/upload/props.usdz[maps/wood.png]`, which check_layers checked), a
    copy of that entry under work/packaged (read with zipfile; the package must be a file of the
    upload and hold the entry)."""
    from pxr import Ar

    if not resolved or not Ar.IsPackageRelativePath(resolved):
        return resolved
    package, inner = Ar.SplitPackageRelativePathOuter(resolved)
    target = Path(os.path.realpath(package))
    if Ar.IsPackageRelativePath(inner) or not target.is_relative_to(root) or not target.is_file():
        raise SceneError(f"{where}: the asset {resolved!r} is not a file of the upload",
                         _field(where))  # fmt: skip
    try:
        with zipfile.ZipFile(target) as archive:
            data = archive.read(inner)
    except (KeyError, zipfile.BadZipFile, OSError) as e:
        raise SceneError(f"{where}: the asset {resolved!r} cannot be read from its package",
                         _field(where)) from e  # fmt: skip
    out = work / "packaged" / (hashlib.sha256(resolved.encode()).hexdigest()[:16] +
                               posixpath.splitext(inner)[1].lower())  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    return str(out)


def check_used_layers(stage, root: Path) -> None:
    """The defence behind check_layers, after composition (and again after the conversion,
    which opens value clips' layers as it reads them): every layer the stage used is a file of
    the upload, or an entry of a .usdz that is one. SceneError names the first that is not."""
    from pxr import Ar

    root = Path(os.path.realpath(root))
    for layer in stage.GetUsedLayers():
        if layer.anonymous:
            continue
        outer = layer.realPath or layer.identifier
        while outer and Ar.IsPackageRelativePath(outer):
            outer = Ar.SplitPackageRelativePathOuter(outer)[0]
        target = Path(os.path.realpath(outer)) if outer else None
        if target is None or not target.is_relative_to(root) or not target.is_file():
            raise SceneError(
                f"the stage composed the layer {_shown(layer.identifier)!r}, which is not a file "
                "of the upload; only files inside the upload are read"
            )


def template_clip_paths(
    template: str, start: float, end: float, stride: float, limit: int = MAX_TEMPLATE_CLIPS
) -> list[str]:
    """The asset paths a value clip template names, as USD derives them
    (Usd_ClipSetDefinition): the file name's '.'-separated tokens (empty ones dropped) hold one
    group of '#' (the time's integer part, zero-padded to the group's width) or two adjacent
    ones (then the second takes the time's fraction to as many digits), for each time from
    `start` to `end` by `stride` (stepped in units of 1/10000, as USD does). No paths where USD
    derives no clips (a stride <= 0, an end before the start, another shape of template);
    ValueError when there would be more than `limit`."""
    if any(math.isnan(v) for v in (start, end, stride)) or stride <= 0 or start > end:
        return []
    head, slash, base = template.rpartition("/")
    tokens = [t for t in base.split(".") if t]
    groups = [i for i, t in enumerate(tokens) if set(t) == {"#"}]
    if len(groups) not in (1, 2) or (len(groups) == 2 and groups[1] != groups[0] + 1):
        return []
    if (end - start) / stride + 1 > limit:
        raise ValueError(f"more than {limit} clips")
    widths = [len(tokens[i]) for i in groups]
    promotion = 10000.0
    out: list[str] = []
    t = start * promotion
    while t <= end * promotion:
        clip_time = t / promotion
        tokens[groups[0]] = f"{int(clip_time):0{widths[0]}d}"
        if len(groups) == 2:
            text = f"{clip_time:.{widths[1]}f}"
            tokens[groups[1]] = text[text.find(".") + 1 :]
        out.append(head + slash + ".".join(tokens))
        t += stride * promotion
    return out


def _arc_items(list_op) -> list[Any]:
    """The references or payloads a list op adds (not those it deletes), each once."""
    items: list[Any] = []
    for attr in ("explicitItems", "addedItems", "prependedItems", "appendedItems"):
        for item in list(getattr(list_op, attr, []) or []):
            if getattr(item, "assetPath", "") and item not in items:
                items.append(item)
    return items


def check_layers(root_layer: Path, root: Path, limit: int = 1000) -> CheckedLayers:
    """Check the root layer and every layer it names (recursively) without composing them;
    return the layers' files, the MaterialX arcs dropped and the open layers. SceneError names
    the first asset path that is refused. A .usdz the layers name is checked from inside: every
    layer in it (see _check_package)."""
    from pxr import Sdf  # imported here: only the conversion's child process needs usd-core

    root = Path(os.path.realpath(root))
    first = Path(os.path.realpath(root_layer))
    if not first.is_relative_to(root):
        raise SceneError("the root layer is outside the upload")
    todo, seen = [first], set()
    checked = CheckedLayers(files=[])
    count = 0
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        count += 1
        if count > limit:
            raise SceneError(f"the stage names more than {limit} layers")
        if path.suffix.lower() not in USD_LAYER_SUFFIXES:
            raise SceneError(
                f"{path.relative_to(root)}: only USD layers ({', '.join(USD_LAYER_SUFFIXES)}) can "
                "be composed",
                _field(str(path.relative_to(root))),
            )
        if path.suffix.lower() == ".usdz":
            count += _check_package(path, root, checked, limit - count)
            continue
        layer = Sdf.Layer.FindOrOpen(str(path))
        if layer is None:
            raise SceneError(f"{path.relative_to(root)} is not a readable USD layer")
        anchor = path.parent

        def check(asset: str, where: str, need_file: bool, anchor: Path = anchor):
            return check_asset_path(asset, anchor, root, where, need_file=need_file)

        arcs, dropped = _checked_arcs(layer, str(path.relative_to(root)), check)
        todo += arcs
        if dropped:
            checked.dropped += dropped
            checked.layers.append(layer)  # edited in memory: kept open for the composition
    checked.files = sorted(seen)
    return checked


def _check_package(package: Path, root: Path, checked: CheckedLayers, limit: int) -> int:
    """Check every USD layer inside a .usdz of the upload where USD reads it, inside the
    package: an asset path there is anchored at its layer's folder in the package
    (`props.usdz[parts/a.usda]` naming `../maps/b.png` is `props.usdz[maps/b.png]`), must stay
    inside the package and name an entry of it (no file beside the package, nothing outside
    the upload); a package inside the package is refused. The first entry is the package's root
    layer (opened as the package itself, as an arc names it). Returns the layers checked."""
    from pxr import Sdf

    rel = str(package.relative_to(root))
    try:
        with zipfile.ZipFile(package) as archive:
            names = [i.filename for i in archive.infolist() if not i.is_dir()]
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise SceneError(f"{rel} is not a readable .usdz package", _field(rel)) from e
    entries = {posixpath.normpath(n) for n in names}
    layers = [n for n in names if n.lower().endswith(USD_LAYER_SUFFIXES)]
    if len(layers) > limit:
        raise SceneError(f"the stage names more than {limit} layers")
    for entry in layers:
        label = f"{rel}[{entry}]"
        if entry.lower().endswith(".usdz"):
            raise SceneError(f"{label}: a package inside a package is not read; upload its "
                             "files instead", _field(label))  # fmt: skip
        identifier = str(package) if entry == names[0] else f"{package}[{entry}]"
        layer = Sdf.Layer.FindOrOpen(identifier)
        if layer is None:
            raise SceneError(f"{label} is not a readable USD layer", _field(label))
        folder = posixpath.dirname(posixpath.normpath(entry))

        def check(asset: str, where: str, need_file: bool, folder: str = folder):
            return _check_packaged_path(asset, folder, entries, rel, where, need_file)

        try:
            arcs, dropped = _checked_arcs(layer, label, check)
        except SceneError as e:
            raise SceneError(f"{label}: {e.message}", e.field) from None
        for arc in arcs:  # every layer of the package is checked here: none to follow
            if arc.suffix.lower() not in (".usd", ".usda", ".usdc"):
                raise SceneError(f"{label}: {arc} inside the package is no USD layer that can "
                                 "be composed (.usd, .usda, .usdc)", _field(label))  # fmt: skip
        if dropped:
            checked.dropped += dropped
            checked.layers.append(layer)
    return len(layers)


def _check_packaged_path(
    path: str, folder: str, entries: set[str], package: str, where: str, need_file: bool
) -> PurePosixPath | None:
    """The package entry an asset path of a layer inside `package` names (see _check_package),
    or SceneError naming `where`; None for an empty path, a UDIM set, or (without `need_file`)
    no entry."""
    if not path:
        return None
    _check_written(path, where)
    inner = posixpath.normpath(posixpath.join(folder, path.replace("\\", "/")))
    if inner == ".." or inner.startswith("../"):
        raise SceneError(
            f"{where}: the asset path {_shown(path)!r} climbs out of the package {package} with "
            "'..'; a packaged layer reads files of its package only",
            _field(where),
        )
    if is_udim(path):
        return None
    if inner not in entries:
        if not need_file:
            return None
        raise SceneError(
            f"{where}: the asset path {_shown(path)!r} names no file of the package {package}",
            _field(where),
        )
    return PurePosixPath(inner)


def _checked_arcs(layer, name: str, check) -> tuple[list[Any], list[DroppedArc]]:
    """Check every asset path of one layer with `check(asset, where, need_file)` (the file it
    names, or None); return the layers its arcs name, and the arcs to MaterialX documents, which
    are removed from the layer (in memory)."""
    from pxr import Sdf

    arcs: list[Any] = []
    dropped: list[DroppedArc] = []
    removals: list[tuple[Any, str, Any]] = []  # (spec path, "references"/"payload", item)

    def visit(
        where: str, asset: str, composed: bool, arc: tuple | None = None, optional: bool = False
    ) -> None:
        target = check(asset, where, not optional)
        if not composed or target is None:
            return
        if arc is not None and target.suffix.lower() == MATERIALX_SUFFIX:
            removals.append(arc[2:])
            dropped.append(DroppedArc(arc[0], arc[1], asset, _variant_of(arc[2])))
        else:
            arcs.append(target)

    for i, sub in enumerate(layer.subLayerPaths):
        visit(f"{name}.subLayers[{i}]", sub, True, (name, "sublayer", None, "subLayers", sub))
    problems: list[SceneError] = []

    def spec(sdf_path) -> None:
        if problems:
            return
        try:
            _check_spec(layer, sdf_path, visit)
        except SceneError as e:
            problems.append(e)

    layer.Traverse(Sdf.Path.absoluteRootPath, spec)
    if problems:
        raise problems[0]
    for spec_path, kind, item in removals:
        if kind == "subLayers":
            layer.subLayerPaths.remove(item)
            continue
        prim = layer.GetPrimAtPath(spec_path)
        (prim.referenceList if kind == "references" else prim.payloadList).RemoveItemEdits(item)
    return arcs, dropped


def _variant_of(spec_path) -> str:
    """ "set=selection" of the innermost variant a prim spec path lies in ("" for none)."""
    if spec_path is None:
        return ""
    for prefix in reversed(spec_path.GetPrefixes()):
        if prefix.IsPrimVariantSelectionPath():
            variant_set, selection = prefix.GetVariantSelection()
            return f"{variant_set}={selection}"
    return ""


def _check_spec(layer, sdf_path, visit) -> None:
    from pxr import Sdf

    if sdf_path.IsPrimPath() or sdf_path.IsPrimVariantSelectionPath():
        prim = layer.GetPrimAtPath(sdf_path)
        if prim is None:
            return
        where = str(sdf_path.StripAllVariantSelections())
        for item in _arc_items(prim.referenceList):
            arc = (where, "reference", sdf_path, "references", item)
            visit(f"{where}.references", item.assetPath, True, arc)
        for item in _arc_items(prim.payloadList):
            arc = (where, "payload", sdf_path, "payload", item)
            visit(f"{where}.payload", item.assetPath, True, arc)
        clips = prim.GetInfo("clips") if prim.HasInfo("clips") else {}
        for clip_set, value in dict(clips).items():
            for key in ("assetPaths", "manifestAssetPath"):
                entries = value.get(key)
                if entries is None:
                    continue
                for entry in entries if isinstance(entries, (list, tuple)) else [entries]:
                    visit(f"{where}.clips[{clip_set}].{key}", _asset_text(entry), True)
            if value.get("templateAssetPath") is not None:
                _check_template(f"{where}.clips[{clip_set}].templateAssetPath", value, visit)
        return
    if not sdf_path.IsPropertyPath():
        return
    attr = layer.GetAttributeAtPath(sdf_path)
    if attr is None:
        return
    if attr.typeName not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
        return
    where = str(sdf_path.StripAllVariantSelections())
    # A shader's source module (info:mdl:sourceAsset = @OmniPBR.mdl@, from the renderer's
    # search path) is never read: it must stay inside the upload but need not be in it.
    never_read = _SOURCE_ASSET.match(attr.name) is not None
    values = [attr.default] if attr.HasDefaultValue() else []
    values += [layer.QueryTimeSample(sdf_path, t) for t in layer.ListTimeSamplesForPath(sdf_path)]
    for value in values:
        single = value is None or isinstance(value, str) or hasattr(value, "path")
        for item in [value] if single else list(value):
            visit(where, _asset_text(item), False, optional=never_read)


def _check_template(where: str, clips: dict, visit) -> None:
    """A value clip template: the template itself must stay inside the upload; each clip it
    names over its times (when this layer authors them: USD composes the clip set's fields
    across layers, and clips another layer's times name are caught after composition by
    check_used_layers) is checked as an asset path, and the files that exist as layers."""
    template = str(clips.get("templateAssetPath") or "")
    visit(where, template, False, optional=True)
    times = [clips.get(k) for k in ("templateStartTime", "templateEndTime", "templateStride")]
    if any(not isinstance(t, (int, float)) for t in times):
        return
    try:
        paths = template_clip_paths(template, *(float(t) for t in times))
    except ValueError:
        raise SceneError(
            f"{where}: the template {_shown(template)!r} names more than {MAX_TEMPLATE_CLIPS} "
            "clips over its times",
            _field(where),
        ) from None
    for path in paths:
        visit(where, path, True, optional=True)


def _asset_text(value) -> str:
    if value is None:
        return ""
    return value.path if hasattr(value, "path") else str(value)


__all__ = [
    "USD_LAYER_SUFFIXES",
    "backslashed_path",
    "CheckedLayers",
    "DroppedArc",
    "check_asset_path",
    "check_layers",
    "check_used_layers",
    "is_udim",
    "packaged_copy",
    "read_inside",
    "template_clip_paths",
]

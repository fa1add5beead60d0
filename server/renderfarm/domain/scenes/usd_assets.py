"""What a USD upload may refer to: files of the upload, and nothing else.

Before a stage is composed (which opens every layer it names), every layer of the upload is read
on its own with Sdf, without composition, and every asset path in it is checked: sublayers,
references, payloads, value clips and every asset-valued attribute (defaults and time samples,
in variants too). An asset path must be relative, stay inside the upload's directory after
`..` and symbolic links are resolved, name a file that is there, and be no URL, absolute path,
package path (`a.usdz[b.usd]`) or search path outside the upload; a UDIM tile set
(`tex.<UDIM>.png`) is never read (the converter warns and uses the texture's
fallback). A refusal is a SceneError
whose field names the layer's prim and attribute as USD writes a property path
(`scene:/World/Looks/Wood/Texture.inputs:file`). Layers the checked arcs name are checked in
turn, before anything opens them; only then may Usd.Stage.Open compose the stage.

A sublayer, reference or payload naming a MaterialX document (`.mtlx`, as the USD Working
Group's assets and Houdini's exports compose their materials) is checked like any asset path,
then dropped from its layer in memory (never opened: usd-core has no MaterialX file format, and
the converter reads UsdPreviewSurface only) and listed in `CheckedLayers.dropped`, which the
converter warns about, one warning an arc. The edited layers stay open in `CheckedLayers.layers`
so that the stage composes them, not the files.

The converter reads texture bytes through `read_inside`, which checks the resolved path again,
so that a path the checks missed can still read nothing outside the upload.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...errors import SceneError

USD_LAYER_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
MATERIALX_SUFFIX = ".mtlx"


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


_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*:")


def _field(where: str) -> str:
    return f"scene:{where}"


def check_asset_path(path: str, anchor_dir: Path, root: Path, where: str) -> Path | None:
    """The file an asset path names, inside `root`, or SceneError naming `where` (a prim path
    and attribute, or a layer's sublayer). An empty path names nothing (None)."""
    if not path:
        return None
    shown = path if len(path) <= 200 else path[:200] + "..."
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
    # A '..' may climb to a folder of the upload (layers/shot.usda naming ../maps/wood.png, as
    # packaged assets do), not above it: checked on the path as written, before any symbolic
    # link is resolved (then again on the resolved path, below).
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
        raise SceneError(
            f"{where}: the asset path {shown!r} names no file of the upload", _field(where)
        )
    return target


def is_udim(path: str) -> bool:
    """Whether an asset path names a UDIM tile set (`tex.<UDIM>.png`)."""
    upper = path.upper()
    return "<UDIM>" in upper or "<UVTILE" in upper


def read_inside(path: str, root: Path, where: str) -> bytes:
    """The bytes of a resolved asset path, which must be a file inside `root`."""
    target = Path(os.path.realpath(path)) if path else None
    if target is None or not target.is_relative_to(root) or not target.is_file():
        raise SceneError(f"{where}: the asset {path!r} is not a file of the upload", _field(where))
    return target.read_bytes()


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
    the first asset path that is refused."""
    from pxr import Sdf  # imported here: only the conversion's child process needs usd-core

    root = Path(os.path.realpath(root))
    first = Path(os.path.realpath(root_layer))
    if not first.is_relative_to(root):
        raise SceneError("the root layer is outside the upload")
    todo, seen = [first], set()
    checked = CheckedLayers(files=[])
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        if len(seen) > limit:
            raise SceneError(f"the stage names more than {limit} layers")
        if path.suffix.lower() not in USD_LAYER_SUFFIXES:
            raise SceneError(
                f"{path.relative_to(root)}: only USD layers ({', '.join(USD_LAYER_SUFFIXES)}) can "
                "be composed",
                _field(str(path.relative_to(root))),
            )
        layer = Sdf.Layer.FindOrOpen(str(path))
        if layer is None:
            raise SceneError(f"{path.relative_to(root)} is not a readable USD layer")
        arcs, dropped = _checked_arcs(layer, path, root)
        todo += arcs
        if dropped:
            checked.dropped += dropped
            checked.layers.append(layer)  # edited in memory: kept open for the composition
    checked.files = sorted(seen)
    return checked


def _checked_arcs(layer, path: Path, root: Path) -> tuple[list[Path], list[DroppedArc]]:
    """Check every asset path of one layer; return the layers its arcs name, and the arcs to
    MaterialX documents, which are removed from the layer (in memory)."""
    from pxr import Sdf

    anchor = path.parent
    name = str(path.relative_to(root))
    arcs: list[Path] = []
    dropped: list[DroppedArc] = []
    removals: list[tuple[Any, str, Any]] = []  # (spec path, "references"/"payload", item)

    def visit(where: str, asset: str, composed: bool, arc: tuple | None = None) -> None:
        target = check_asset_path(asset, anchor, root, where)
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
        return
    if not sdf_path.IsPropertyPath():
        return
    attr = layer.GetAttributeAtPath(sdf_path)
    if attr is None:
        return
    if attr.typeName not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
        return
    where = str(sdf_path.StripAllVariantSelections())
    values = [attr.default] if attr.HasDefaultValue() else []
    values += [layer.QueryTimeSample(sdf_path, t) for t in layer.ListTimeSamplesForPath(sdf_path)]
    for value in values:
        single = value is None or isinstance(value, str) or hasattr(value, "path")
        for item in [value] if single else list(value):
            visit(where, _asset_text(item), False)


def _asset_text(value) -> str:
    if value is None:
        return ""
    return value.path if hasattr(value, "path") else str(value)


__all__ = [
    "USD_LAYER_SUFFIXES",
    "CheckedLayers",
    "DroppedArc",
    "check_asset_path",
    "check_layers",
    "is_udim",
    "read_inside",
]

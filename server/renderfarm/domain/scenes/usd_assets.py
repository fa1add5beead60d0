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

The converter reads texture bytes through `read_inside`, which checks the resolved path again,
so that a path the checks missed can still read nothing outside the upload.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ...errors import SceneError

USD_LAYER_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

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


def _arc_paths(list_op) -> list[str]:
    items = []
    for attr in ("explicitItems", "addedItems", "prependedItems", "appendedItems"):
        items += list(getattr(list_op, attr, []) or [])
    return [item.assetPath for item in items if getattr(item, "assetPath", "")]


def check_layers(root_layer: Path, root: Path, limit: int = 1000) -> list[Path]:
    """Check the root layer and every layer it names (recursively) without composing them;
    return the layers' files. SceneError names the first asset path that is refused."""
    from pxr import Sdf  # imported here: only the conversion's child process needs usd-core

    root = Path(os.path.realpath(root))
    first = Path(os.path.realpath(root_layer))
    if not first.is_relative_to(root):
        raise SceneError("the root layer is outside the upload")
    todo, seen = [first], set()
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
        todo += _checked_arcs(layer, path, root)
    return sorted(seen)


def _checked_arcs(layer, path: Path, root: Path) -> list[Path]:
    """Check every asset path of one layer; return the layers its arcs name."""
    from pxr import Sdf

    anchor = path.parent
    name = str(path.relative_to(root))
    arcs: list[Path] = []

    def visit(where: str, asset: str, composed: bool) -> None:
        target = check_asset_path(asset, anchor, root, where)
        if composed and target is not None:
            arcs.append(target)

    for i, sub in enumerate(layer.subLayerPaths):
        visit(f"{name}.subLayers[{i}]", sub, True)
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
    return arcs


def _check_spec(layer, sdf_path, visit) -> None:
    from pxr import Sdf

    if sdf_path.IsPrimPath() or sdf_path.IsPrimVariantSelectionPath():
        prim = layer.GetPrimAtPath(sdf_path)
        if prim is None:
            return
        where = str(sdf_path.StripAllVariantSelections())
        for asset in _arc_paths(prim.referenceList):
            visit(f"{where}.references", asset, True)
        for asset in _arc_paths(prim.payloadList):
            visit(f"{where}.payload", asset, True)
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


__all__ = ["USD_LAYER_SUFFIXES", "check_asset_path", "check_layers", "is_udim", "read_inside"]

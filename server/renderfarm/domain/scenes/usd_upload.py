"""USD uploads told apart from glTF ones, and laid out as the files the conversion reads.

An upload is USD when it is a crate file (`PXR-USDC`), a text layer (`#usda`), a .usdz package
(a zip whose first entry is a USD layer, as the USDZ specification requires) or a .zip/.tar
bundle holding USD layers and no .gltf. The files come from bundles.read_bundle, with its checks
(relative paths only, no links, entry count and size limits); the root layer is the package's
first layer, or the one USD layer nearest the bundle's top (a .usd/.usda/.usdc layer before the
.usdz packages beside it).
"""

from __future__ import annotations

import io
import posixpath
import tarfile
import zipfile

from ...errors import SceneError
from .bundles import EMPTY_ZIP_MAGIC, ZIP_MAGIC, is_bundle, read_bundle

USDC_MAGIC = b"PXR-USDC"
USDA_MAGIC = b"#usda"
LAYER_SUFFIXES = (".usd", ".usda", ".usdc")
USD_SUFFIXES = (*LAYER_SUFFIXES, ".usdz")


def _names(data: bytes) -> list[str]:
    """Entry names of a zip or tar upload in archive order ([] when unreadable)."""
    try:
        if data[:4] in (ZIP_MAGIC, EMPTY_ZIP_MAGIC):
            with zipfile.ZipFile(io.BytesIO(data)) as archive:
                return [i.filename for i in archive.infolist() if not i.is_dir()]
        with tarfile.open(fileobj=io.BytesIO(data), mode="r|*") as archive:
            return [m.name for m in archive if m.isfile()]
    except (zipfile.BadZipFile, tarfile.TarError, OSError, EOFError, ValueError):
        return []


def usd_kind(data: bytes | None, filename: str = "") -> str | None:
    """ "usdc", "usda", "usdz", "bundle" or None (not USD), by content."""
    if not data:
        return None
    if data.startswith(USDC_MAGIC):
        return "usdc"
    if data.lstrip(b"\xef\xbb\xbf").startswith(USDA_MAGIC):
        return "usda"
    if not is_bundle(data):
        return None
    names = _names(data)
    if not names:
        return None
    if data[:4] == ZIP_MAGIC and names[0].lower().endswith(LAYER_SUFFIXES):
        if filename.lower().endswith(".usdz") or not any(
            n.lower().endswith(".gltf") for n in names
        ):
            return "usdz" if filename.lower().endswith(".usdz") else "bundle"
    if any(n.lower().endswith(".gltf") for n in names):
        return None
    if any(n.lower().endswith(USD_SUFFIXES) for n in names):
        return "bundle"
    return None


def usd_files(data: bytes, filename: str, kind: str, limit: int) -> tuple[dict[str, bytes], str]:
    """(the upload's files by relative path, the root layer's path among them)."""
    name = posixpath.basename(filename.replace("\\", "/")) or "scene"
    if kind in ("usdc", "usda"):
        stem = posixpath.splitext(name)[0] or "scene"
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in stem) or "scene"
        return {f"{stem}.{kind}": data}, f"{stem}.{kind}"
    files = read_bundle(data, name, limit)
    if kind == "usdz":
        first = _names(data)[0]
        root = posixpath.normpath(first.replace("\\", "/"))
        if root not in files:
            raise SceneError(f"{name}: the package's first entry {first!r} cannot be read")
        return files, root
    layers = [p for p in files if p.lower().endswith(USD_SUFFIXES)]
    if not layers:
        raise SceneError(f"{name} holds no USD layer (.usd, .usda, .usdc or .usdz)")
    depth = min(p.count("/") for p in layers)
    top = sorted(p for p in layers if p.count("/") == depth)
    if len(top) > 1:  # a shot's layer beside the packages it references is the root layer
        top = [p for p in top if not p.lower().endswith(".usdz")] or top
    if len(top) != 1:
        raise SceneError(
            f"{name} must hold one USD layer nearest its top, the stage's root layer "
            f"(found {', '.join(top[:5])})"
        )
    return files, top[0]


__all__ = ["USD_SUFFIXES", "usd_files", "usd_kind"]

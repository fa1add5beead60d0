"""Scene bundles: a .gltf with its buffers and textures uploaded as one .zip or .tar(.gz).

A bundle is read in memory only (nothing is ever written to disk), checked entry by entry, and
packed into a single .glb (pack.pack_gltf_files), so workers always receive one .glb. Refused,
with SceneError(field "scene") naming the entry: absolute paths, `..` components, drive letters,
symlinks, hard links and device files, more than MAX_ENTRIES entries, duplicate names, a total
uncompressed size over the upload limit (TooLarge), and bundles without exactly one .gltf.
"""

from __future__ import annotations

import io
import posixpath
import tarfile
import zipfile

from ...errors import SceneError, TooLarge
from .pack import pack_gltf_files

MAX_ENTRIES = 1000
ZIP_MAGIC = b"PK\x03\x04"
EMPTY_ZIP_MAGIC = b"PK\x05\x06"
GZIP_MAGIC = b"\x1f\x8b"


def is_bundle(data: bytes) -> bool:
    """Whether an upload is a zip or tar archive (by content, not by name)."""
    if data[:4] in (ZIP_MAGIC, EMPTY_ZIP_MAGIC) or data[:2] == GZIP_MAGIC:
        return True
    return len(data) >= 512 and data[257:262] == b"ustar"


def _entry_path(raw: str, bundle: str) -> str:
    """The normalised relative path of an archive entry, or SceneError."""
    shown = raw if len(raw) <= 200 else raw[:200] + "..."
    if "\0" in raw:
        raise SceneError(f"{bundle}: entry {shown!r} has a NUL character in its name")
    path = raw.replace("\\", "/")
    if path.startswith("/") or (len(path) >= 2 and path[1] == ":"):
        raise SceneError(f"{bundle}: entry {shown!r} is an absolute path; only relative paths")
    parts = [p for p in path.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise SceneError(f"{bundle}: entry {shown!r} climbs out of the bundle with '..'")
    return posixpath.join(*parts) if parts else ""


def _add(files: dict[str, bytes], path: str, data: bytes, bundle: str) -> None:
    if path in files:
        raise SceneError(f"{bundle}: entry {path!r} appears twice")
    files[path] = data


def _check_count(count: int, bundle: str) -> None:
    if count > MAX_ENTRIES:
        raise SceneError(f"{bundle} has {count} entries, more than the limit of {MAX_ENTRIES}")


def _too_large(bundle: str, limit: int) -> TooLarge:
    return TooLarge("scene", f"{bundle} unpacks to more than the upload limit of {limit} bytes")


def _read_zip(data: bytes, bundle: str, limit: int) -> dict[str, bytes]:
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise SceneError(f"{bundle} is not a readable zip archive: {e}") from None
    with archive:
        infos = archive.infolist()
        _check_count(len(infos), bundle)
        files: dict[str, bytes] = {}
        total = 0
        for info in infos:
            path = _entry_path(info.filename, bundle)
            mode = info.external_attr >> 16
            if mode and (mode & 0o170000) not in (0, 0o100000, 0o040000):
                kind = "a symlink" if (mode & 0o170000) == 0o120000 else "not a regular file"
                raise SceneError(f"{bundle}: entry {info.filename!r} is {kind}; refused")
            if info.is_dir() or not path:
                continue
            total += info.file_size
            if total > limit:
                raise _too_large(bundle, limit)
            try:
                with archive.open(info) as member:
                    content = member.read(info.file_size + 1)
            except (zipfile.BadZipFile, OSError, ValueError, NotImplementedError) as e:
                raise SceneError(f"{bundle}: entry {info.filename!r} cannot be read: {e}") from None
            if len(content) != info.file_size:  # a lying header: never trust it for the limit
                raise SceneError(f"{bundle}: entry {info.filename!r} is not the size it declares")
            _add(files, path, content, bundle)
        return files


def _read_tar(data: bytes, bundle: str, limit: int) -> dict[str, bytes]:
    files: dict[str, bytes] = {}
    total = 0
    count = 0
    try:
        # Stream mode: members are read in order, nothing is seeked or extracted to disk, and a
        # gzip bomb stops at the size limit below instead of being inflated first.
        with tarfile.open(fileobj=io.BytesIO(data), mode="r|*") as archive:
            for member in archive:
                count += 1
                _check_count(count, bundle)
                path = _entry_path(member.name, bundle)
                if member.issym() or member.islnk():
                    kind = "a symlink" if member.issym() else "a hard link"
                    raise SceneError(f"{bundle}: entry {member.name!r} is {kind}; refused")
                if member.isdir():
                    continue
                if not member.isfile():
                    raise SceneError(f"{bundle}: entry {member.name!r} is not a regular file")
                if not path:
                    continue
                total += member.size
                if total > limit:
                    raise _too_large(bundle, limit)
                handle = archive.extractfile(member)
                content = handle.read() if handle is not None else b""
                _add(files, path, content, bundle)
    except (tarfile.TarError, OSError, EOFError) as e:
        raise SceneError(f"{bundle} is not a readable tar archive: {e}") from None
    return files


def read_bundle(data: bytes, filename: str, limit: int) -> dict[str, bytes]:
    """Every regular file of a zip or tar(.gz) bundle by normalised relative path."""
    bundle = filename or "bundle"
    if len(data) > limit:
        raise TooLarge("scene", f"{bundle} is {len(data)} bytes, over the limit of {limit} bytes")
    if data[:4] in (ZIP_MAGIC, EMPTY_ZIP_MAGIC):
        return _read_zip(data, bundle, limit)
    return _read_tar(data, bundle, limit)


def bundle_to_glb(data: bytes, filename: str, limit: int) -> tuple[bytes, str]:
    """(the .glb packed from a bundle's one .gltf and its files, the .glb's file name)."""
    bundle = filename or "bundle"
    files = read_bundle(data, bundle, limit)
    gltfs = sorted(p for p in files if p.lower().endswith(".gltf"))
    if len(gltfs) != 1:
        found = ", ".join(gltfs[:5]) if gltfs else "none"
        raise SceneError(f"{bundle} must hold exactly one .gltf file (found {found})")
    glb = pack_gltf_files(files, gltfs[0], max_bytes=limit)
    return glb, posixpath.splitext(posixpath.basename(gltfs[0]))[0] + ".glb"


def scene_upload(data: bytes | None, filename: str, limit: int) -> tuple[bytes | None, str]:
    """An uploaded scene as the server stores it: bundles become a .glb; anything else is
    passed on unchanged (inspect_scene checks it)."""
    if data is None or not is_bundle(data):
        return data, filename
    return bundle_to_glb(data, filename, limit)


__all__ = ["MAX_ENTRIES", "bundle_to_glb", "is_bundle", "read_bundle", "scene_upload"]

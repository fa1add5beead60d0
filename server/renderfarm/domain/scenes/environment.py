"""Environment maps as uploaded: a Radiance .hdr or an OpenEXR image, told by signature."""

from __future__ import annotations

import hashlib

from ...errors import SceneError

_HDR_MAGICS = (b"#?RADIANCE", b"#?RGBE")

_EXR_MAGIC = b"\x76\x2f\x31\x01"


def inspect_environment(
    data: bytes, filename: str = "", max_bytes: int = 256 * 2**20
) -> tuple[str, str]:
    """Check that `data` is a Radiance .hdr or OpenEXR image; return (sha256, "hdr" | "exr").

    Only the file signature is checked here; workers decode the image with OpenImageIO and
    report a non-retryable failure if it is corrupt."""
    name = filename or "environment"
    if not data:
        raise SceneError(f"{name} is empty", "environment")
    if len(data) > max_bytes:
        raise SceneError(
            f"{name} is {len(data)} bytes, over the limit of {max_bytes}", "environment"
        )
    if data.startswith(_EXR_MAGIC):
        fmt = "exr"
    elif any(data.startswith(m) for m in _HDR_MAGICS):
        fmt = "hdr"
    else:
        raise SceneError(
            f"{name} is not an environment map: expected a Radiance .hdr or an OpenEXR .exr image",
            "environment",
        )
    return hashlib.sha256(data).hexdigest(), fmt

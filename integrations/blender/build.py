"""Builds the add-on's zip, which Blender installs (Edit > Preferences > Get Extensions >
Install from Disk, or `blender --command extension install-file -r user_default ZIP`).

    python integrations/blender/build.py build/renderfarm-blender.zip

The zip holds the package's files at its root, blender_manifest.toml among them, as Blender's
own `blender --command extension build` lays an extension out; caches are left out. Entries
are written in name order with a fixed date, so the same sources give the same bytes.
"""

from __future__ import annotations

import sys
import zipfile
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent / "renderfarm_blender"
FIXED_DATE = (2024, 1, 1, 0, 0, 0)


def build(out: Path) -> Path:
    files = sorted(
        p
        for p in PACKAGE.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts and p.suffix not in (".pyc", ".pyo")
    )
    if not (PACKAGE / "blender_manifest.toml").is_file():
        raise SystemExit(f"no blender_manifest.toml in {PACKAGE}")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for path in files:
            info = zipfile.ZipInfo(path.relative_to(PACKAGE).as_posix(), FIXED_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            z.writestr(info, path.read_bytes())
    tmp.replace(out)
    return out


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: build.py OUT.zip")
    print(build(Path(sys.argv[1])))

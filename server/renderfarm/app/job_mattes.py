"""What a pixel of a job's Cryptomatte holds (docs/usage.md, "Cryptomatte"): the names of the
nodes, materials and root nodes its samples hit, with their coverage. The dashboard names the
object under the pointer with it; a script can ask the same of any pixel.

Read from the tile holding the pixel: in memory while the job is held (a snapshot of two arrays,
from RAM or a spill file), else from its checkpoint. The scene's names are parsed from its glTF
JSON once per scene and kept (MAX_CACHED_NAMES scenes, least recently used dropped first).
"""

from __future__ import annotations

import asyncio
import math
from collections import OrderedDict
from typing import Any

import numpy as np

from ..domain import channels, cryptomatte
from ..domain.frames import frame_slot, job_rects, tiles_per_frame
from ..errors import SettingsError
from ..infra import images
from . import checkpoints
from .auth import Caller

MAX_CACHED_NAMES = 16  # scenes whose Cryptomatte names are kept
_ARRAYS = ("crypto_object", "crypto_material")


class JobMattes:
    """Part of FarmService (jobs.py): uses its get, store, scheduler and _crypto_names
    (job_images.py)."""

    _names_cache: OrderedDict[str, cryptomatte.Names] | None = None

    async def cached_crypto_names(self, sha256: str) -> cryptomatte.Names:
        """The scene's Cryptomatte names, parsed once per scene for every image and query."""
        if self._names_cache is None:
            self._names_cache = OrderedDict()
        names = self._names_cache.get(sha256)
        if names is None:
            names = await self._crypto_names(sha256)
            self._names_cache[sha256] = names
            while len(self._names_cache) > MAX_CACHED_NAMES:
                self._names_cache.popitem(last=False)
        self._names_cache.move_to_end(sha256)
        return names

    async def pixel_mattes(
        self, job_id: str, x: int, y: int, frame: int | None, caller: Caller
    ) -> dict[str, Any]:
        """The Cryptomatte of pixel (x, y) (x from the left, y from the top) of one image of the
        job: per type the ranked names and their coverage. SettingsError naming `layer` for a
        job without settings.aovs naming cryptomatte, `x` or `y` outside the image; NotFound
        (field `frame`) for an image the job does not have, NotFound / Forbidden as get."""
        view = await self.get(job_id, caller)  # raises NotFound / Forbidden
        settings = view.settings
        layout = channels.job_layout(settings)
        if "crypto_object" not in layout.names:
            raise SettingsError(
                "layer",
                f"job {job_id} was submitted without settings.aovs naming cryptomatte: it has "
                "no Cryptomatte",
            )
        for name, value, size in (("x", x, settings.width), ("y", y, settings.height)):
            if not 0 <= value < size:
                raise SettingsError(name, f"{name} must be in 0..{size - 1}, not {value}")
        slot = frame_slot(settings, frame, view.variants)
        rects = job_rects(settings, view.variants)
        cols = math.ceil(settings.width / settings.tile_size)
        index = (
            slot * tiles_per_frame(settings)
            + (y // settings.tile_size) * cols
            + x // settings.tile_size
        )
        rect = rects[index]
        live = self.scheduler.jobs.get(job_id)
        if live is not None:
            tile_view = images.TileView.of(rect, live.tiles[index].acc, _ARRAYS)
            acc = tile_view and await asyncio.to_thread(tile_view.accumulator)
        else:
            stored = await self.store.load_tiles(job_id, first=index, count=1)
            band = await asyncio.to_thread(
                checkpoints.band_from_rows, settings, rects, index, 1, stored
            )
            acc = band[0][1]
        names = await self.cached_crypto_names(view.scene_sha256)
        samples = 0
        if acc is not None:  # the pixel's own count (per-pixel adaptive sampling) or the tile's
            n = acc.pixel_samples()
            samples = int(n[y - rect.y0, x - rect.x0]) if isinstance(n, np.ndarray) else n
        out: dict[str, Any] = {"x": x, "y": y, "samples": samples}
        for key, type_name, array in (
            ("objects", "CryptoObject", "crypto_object"),
            ("materials", "CryptoMaterial", "crypto_material"),
            ("assets", "CryptoAsset", "crypto_object"),
        ):
            out[key] = [] if acc is None else _ranked_names(
                acc, array, type_name, names, x - rect.x0, y - rect.y0, samples
            )  # fmt: skip
        return out


def _ranked_names(
    acc, array: str, type_name: str, names: cryptomatte.Names, i: int, j: int, samples: int
) -> list[dict[str, Any]]:
    pairs = getattr(acc, array).reshape(acc.height, acc.width, -1)[j : j + 1, i : i + 1]
    if type_name == "CryptoAsset":
        pairs = cryptomatte.regroup(pairs, names.roots)
    by_label = names.label_names(type_name)
    out = []
    for r in range(cryptomatte.RANKS):
        label, count = int(pairs[0, 0, 2 * r]), int(pairs[0, 0, 2 * r + 1])
        if label and label in by_label:
            name = by_label[label]
            out.append({
                "name": name,
                "id": f"{cryptomatte.hash_bits(name):08x}",
                "coverage": count / max(1, samples),
            })  # fmt: skip
    return out

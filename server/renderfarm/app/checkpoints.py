"""Checkpoint serialisation: tiles to database rows (snapshots taken on the loop, bytes made in
a thread) in chunks of about CHECKPOINT_CHUNK_BYTES, and rows back to accumulators.
"""

from __future__ import annotations

from ..domain.channels import job_layout
from ..domain.frames import job_rects
from ..domain.jobspec import JobSettings
from ..domain.merge import TileAccumulator
from ..domain.scheduler import Scheduler
from ..domain.tiling import Rect
from ..infra import images
from ..infra.store import TileRow


def restore_tiles(
    settings: JobSettings, rows: list[TileRow], variants: tuple[str, ...] = ()
) -> dict[int, tuple[Rect, TileAccumulator]]:
    """Checkpointed tiles of a job as accumulators, by tile index (`variants`: those of a job
    of every variant, as stored with it)."""
    rects = job_rects(settings, variants)
    restored = {}
    for t in rows:
        rect = rects[t.tile_index]
        acc = TileAccumulator.from_bytes(
            rect.width,
            rect.height,
            t.accumulators,
            t.samples,
            t.batches,
            t.nonfinite,
            iid=settings.sampler == "independent",
            aovs=t.aovs,
            layout=job_layout(settings),
        )
        restored[t.tile_index] = (rect, acc)
    return restored


CHECKPOINT_CHUNK_BYTES = 32 * 2**20


def chunks(tiles: list) -> list[list]:
    """Tiles in runs of about CHECKPOINT_CHUNK_BYTES of accumulators (at least one each)."""
    chunks, chunk, size = [], [], 0
    for t in tiles:
        if chunk and size + t.acc.nbytes > CHECKPOINT_CHUNK_BYTES:
            chunks.append(chunk)
            chunk, size = [], 0
        chunk.append(t)
        size += t.acc.nbytes
    return chunks + [chunk] if chunk else chunks


def dirty_bytes(tiles, taken=None) -> int:
    """Bytes a checkpoint writes for these tiles (statistics, and AOVs where they changed)."""
    aovs = [a for _, a in taken] if taken is not None else [t.aovs_dirty for t in tiles]
    return sum(
        t.rect.pixels * t.acc.layout.bytes_per_pixel(None if with_aovs else False)
        for t, with_aovs in zip(tiles, aovs, strict=True)
    )


def tile_snapshot(t, with_aovs: bool) -> tuple:
    acc = t.acc
    aovs = acc.aov_snapshot() if with_aovs else None
    plan = None if t.stopped else Scheduler.planned_batches(t) or None
    basis = Scheduler.plan_basis(t) or None
    return (
        t.index, acc.samples, acc.batches, acc.nonfinite, t.error, acc.snapshot(), aovs, t.stop,
        plan, basis,
    )  # fmt: skip


def tile_row(index, samples, batches, nonfinite, error, arrays, aovs, stop, plan, basis) -> TileRow:
    return TileRow(
        tile_index=index,
        samples=samples,
        batches=batches,
        nonfinite=nonfinite,
        error=error,
        accumulators=TileAccumulator.snapshot_bytes(arrays),
        stop_batch=stop.batch_index if stop else None,
        stop_spp=stop.spp if stop else None,
        stop_error=stop.error if stop else None,
        stop_reason=stop.reason.value if stop else None,
        aovs=None if aovs is None else TileAccumulator.snapshot_bytes(aovs),
        batch_plan=plan,
        plan_basis=basis,
    )


def band_from_rows(
    settings: JobSettings, rects: list[Rect], first: int, count: int, rows: list[TileRow]
) -> images.Band:
    """A row of tiles from their checkpoints (a tile without one has no samples)."""
    by_index = {t.tile_index: t for t in rows}
    iid = settings.sampler == "independent"
    layout = job_layout(settings)
    band: images.Band = []
    for index in range(first, first + count):
        rect, t = rects[index], by_index.get(index)
        acc = None
        if t is not None and t.samples > 0:
            acc = TileAccumulator.from_bytes(
                rect.width, rect.height, t.accumulators, t.samples, t.batches, t.nonfinite,
                iid=iid, aovs=t.aovs, layout=layout,
            )  # fmt: skip
        band.append((rect, acc))
    return band

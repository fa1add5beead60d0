"""Continue (docs/architecture.md, "Continue"): whether a completed job's tiles can carry on under
a higher max_spp or a lower noise_threshold and end exactly as a job submitted with the new
settings from the start."""

from __future__ import annotations

import math

from .jobspec import JobSettings
from .tiling import PLANNED_FROM, batch_range, plan_batch

# The settings a continue may change; anything else would change batches already merged.
CONTINUE_SETTINGS = ("max_spp", "noise_threshold")


def _old_size(s: JobSettings, batch: int, basis: dict[int, tuple]) -> int | None:
    """Samples per pixel batch `batch` rendered under settings s (None: not known)."""
    if batch < PLANNED_FROM or s.noise_threshold <= 0:
        return batch_range(batch, s.max_spp)[1]
    entry = basis.get(batch)
    return None if entry is None else entry[0]


def _new_size(s: JobSettings, batch: int, basis: dict[int, tuple]) -> int | None:
    """Samples per pixel a job with settings s would plan for `batch`, from the tile state
    recorded when it was planned (the same state, when every earlier batch agrees)."""
    if batch < PLANNED_FROM or s.noise_threshold <= 0:
        return batch_range(batch, s.max_spp)[1]
    entry = basis.get(batch)
    if entry is None:
        return None
    _, samples, error, before = entry
    error = math.inf if error is None else error
    return plan_batch(samples, error, s.noise_threshold, s.min_spp, s.max_spp, before)


def continue_plan(
    old: JobSettings,
    new: JobSettings,
    merged: int,
    basis: dict[int, tuple],
    pixels_stopped: bool = False,
) -> tuple[list[int], dict[int, tuple]] | None:
    """Whether a tile that merged `merged` batches under `old` can carry on under `new` and
    end exactly as a job submitted with `new` from the start (docs/architecture.md,
    "Continue"): every merged batch must have the size `new` would have given it, which
    tiling's schedule and plan_batch decide from the tile's state when each was planned
    (recorded in `basis`). The stop rule needs no replay: with max_spp no lower and the noise
    threshold no higher, `new` stops a tile no earlier than `old` did.

    Per-pixel adaptive sampling (settings.adaptive pixel): which pixels rendered each batch
    was decided under the old threshold; a lower one would have kept some of them longer. So a
    tile in which a pixel has stopped (`pixels_stopped`) carries on only under the same
    threshold (a higher max_spp), where every decision is the same.

    Returns (planned sizes from batch max(merged, PLANNED_FROM) on, the basis to keep), or
    None: the tile renders again from its first sample."""
    if pixels_stopped and new.noise_threshold != old.noise_threshold:
        return None
    for batch in range(merged):
        size = _old_size(old, batch, basis)
        if size is None or size != _new_size(new, batch, basis):
            return None
    kept = {b: v for b, v in basis.items() if b < merged}
    plans: list[int] = []
    if new.noise_threshold > 0 and merged >= PLANNED_FROM:
        # Batch `merged` was planned from the state after batch merged - 2, which is gone;
        # its recorded basis gives the plan `new` would have made from it.
        count = _new_size(new, merged, basis)
        if count is None:
            return None
        kept[merged] = (count, *basis[merged][1:])
        plans = [count]
    return plans, kept

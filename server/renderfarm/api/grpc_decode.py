"""Worker results as they arrive over gRPC, decoded into the scheduler's BatchResult."""

from __future__ import annotations

import numpy as np

from ..domain import channels
from ..domain.light_groups import MAX_GROUPS
from ..domain.records import BatchResult
from ..domain.tiling import Rect

# What one result may say about its task (TileResult.warnings); more is cut off.
MAX_WARNINGS = 50
MAX_WARNING_CHARS = 1000


_TYPES = {"<f4": 1, "<f8": 2, "<u4": 3}  # workers.proto ValueType
# The rows BatchResult has a field for; the others go to its `extra`.
_FIELDS = frozenset(c.wire for c in channels.DEFAULT.rows)


def _blocks(msg, rect: Rect) -> dict[str, np.ndarray]:
    """The ChannelBlocks of a result by the wire name of their row, checked against the
    channel table: a ValueError naming the block for any mismatch, or for a missing row that
    every job has (the scheduler checks those the job's settings turn on)."""
    if msg.table_version != channels.TABLE_VERSION:
        raise ValueError(
            f"channel table version {msg.table_version}, this server's is {channels.TABLE_VERSION}"
        )
    arrays: dict[str, np.ndarray] = {}
    for block in msg.channels:
        row = channels.BY_NAME.get(block.name)
        if row is None or not row.wire_components:
            raise ValueError(f"channel {block.name[:40]!r} is not one a result carries")
        if row.wire in arrays:
            raise ValueError(f"channel {block.name}: sent twice")
        # A per-group row (light groups) has its components per group: the scheduler checks
        # the count against the job's groups.
        groups = block.components // row.wire_components if row.per_group else 1
        if (
            block.type != _TYPES[row.wire_type]
            or block.components != row.wire_components * groups
            or not 1 <= groups <= MAX_GROUPS
        ):
            expected = f"{row.wire_components}{' x groups' if row.per_group else ''}"
            raise ValueError(
                f"channel {block.name}: type {block.type} x {block.components}, expected "
                f"{_TYPES[row.wire_type]} x {expected}"
            )
        data = block.data  # each read of a bytes field copies it: read once
        size = np.dtype(row.wire_type).itemsize * block.components * rect.pixels
        if len(data) != size:
            raise ValueError(f"channel {block.name}: {len(data)} bytes, expected {size}")
        arrays[row.wire] = np.frombuffer(data, dtype=row.wire_type)
    for row in channels.wire_rows_for(msg.sample_start):
        if row.wire not in arrays:
            raise ValueError(f"channel {row.name}: missing")
    return arrays


def decode_result(msg) -> BatchResult:
    """A TileResult protobuf message as numpy arrays (little-endian, row-major): its
    ChannelBlocks (checked against the channel table), or the fields of a worker from before
    the table."""
    rect = Rect(msg.rect.x0, msg.rect.y0, msg.rect.width, msg.rect.height)
    arrays = _blocks(msg, rect) if msg.channels else _legacy_fields(msg, rect)
    extra = {k: arrays.pop(k) for k in list(arrays) if k not in _FIELDS}
    return BatchResult(
        job_id=msg.job_id,
        tile_index=msg.tile_index,
        batch_index=msg.batch_index,
        sample_start=msg.sample_start,
        sample_count=msg.sample_count,
        rect=rect,
        nonfinite=msg.nonfinite_samples,
        render_seconds=msg.render_seconds,
        rays=msg.rays,
        warnings=tuple(w[:MAX_WARNING_CHARS] for w in msg.warnings[:MAX_WARNINGS]),
        extra=extra,
        **arrays,
    )


def _legacy_fields(msg, rect: Rect) -> dict[str, np.ndarray | None]:
    """The arrays of a worker from before the channel table (no ChannelBlocks): its fields,
    recognised by their length as it sent them."""
    n = rect.pixels
    # Each read of a bytes field copies it out of the message: read each once.
    rgb_raw, m2_raw = msg.rgb_sum, msg.luminance_m2
    albedo_raw, normal_raw = msg.albedo_sum, msg.normal_sum
    # float32 (what workers send) or float64, told apart by length.
    rgb = np.frombuffer(rgb_raw, dtype="<f4" if len(rgb_raw) == 12 * n else "<f8")
    m2 = np.frombuffer(m2_raw, dtype="<f4" if len(m2_raw) == 4 * n else "<f8")
    # AOVs are float32; absent, or of the wrong size, they are left out.
    albedo = np.frombuffer(albedo_raw, dtype="<f4") if len(albedo_raw) == 12 * n else None
    normal = np.frombuffer(normal_raw, dtype="<f4") if len(normal_raw) == 12 * n else None
    coverage_raw = msg.coverage_sum  # float32 counts; absent or of the wrong size: left out
    coverage = np.frombuffer(coverage_raw, dtype="<f4") if len(coverage_raw) == 4 * n else None
    return {
        "rgb_sum": rgb,
        "luminance_m2": m2,
        "albedo_sum": albedo,
        "normal_sum": normal,
        "coverage_sum": coverage,
    }

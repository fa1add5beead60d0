"""Worker results as they arrive over gRPC, decoded into the scheduler's BatchResult."""

from __future__ import annotations

import numpy as np

from ..domain.records import BatchResult
from ..domain.tiling import Rect

# What one result may say about its task (TileResult.warnings); more is cut off.
MAX_WARNINGS = 50
MAX_WARNING_CHARS = 1000


def decode_result(msg) -> BatchResult:
    """A TileResult protobuf message as numpy arrays (little-endian, row-major)."""
    rect = Rect(msg.rect.x0, msg.rect.y0, msg.rect.width, msg.rect.height)
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
    return BatchResult(
        job_id=msg.job_id,
        tile_index=msg.tile_index,
        batch_index=msg.batch_index,
        sample_start=msg.sample_start,
        sample_count=msg.sample_count,
        rect=rect,
        rgb_sum=rgb,
        luminance_m2=m2,
        albedo_sum=albedo,
        normal_sum=normal,
        nonfinite=msg.nonfinite_samples,
        render_seconds=msg.render_seconds,
        rays=msg.rays,
        coverage_sum=coverage,
        warnings=tuple(w[:MAX_WARNING_CHARS] for w in msg.warnings[:MAX_WARNINGS]),
    )

"""Frame lists in the syntax render farms take (OpenCue, Deadline, Flamenco): the `frames`
setting of an animation job.

    7            one frame
    1-120        every frame from 1 to 120
    1-120x2      every second frame: 1, 3, ..., 119
    1,5,10-20    a list of frames and ranges
    -10--1       negative frames (Blender allows them)

The frames of a list are rendered in ascending order, each once, however often the list names
it. A frame number means what the artist saw in Blender: frame f is glTF time f / fps (the glTF
exporter's mapping), frame_time() gives it.

A job with `variant` "all" (KHR_materials_variants) has one image per variant of its scene, in
the scene's order, as an animation has one per frame: its "frames" are the variants' indices
0 .. n-1 and the functions below take the variants' names (stored with the job) beside its
settings. A still has one image, frame 0.
"""

from __future__ import annotations

import bisect
import functools
import re
from typing import Any

from ..errors import NotFound, SettingsError
from .tiling import Rect, tile_grid

_ITEM = re.compile(r"(-?\d+)(?:-(-?\d+)(?:x(\d+))?)?")
MAX_FRAME = 10**6  # frame numbers within +-1e6 (Blender's range is +-1048574)


def parse_frames(text: str, max_frames: int, field: str = "settings.frames") -> tuple[int, ...]:
    """The frames of a list, ascending and unique; SettingsError naming `field` for a list that
    is malformed, has an empty range or a step below 1, or names more than max_frames frames."""
    if not isinstance(text, str) or not text.strip():
        raise SettingsError(field, f"{field} is empty: give frames as 1-120, 1-120x2 or 1,5,10-20")
    frames: set[int] = set()
    for part in text.replace(" ", "").split(","):
        match = _ITEM.fullmatch(part)
        if match is None:
            raise SettingsError(
                field,
                f"{field}: {part[:40]!r} is not a frame, a range a-b or a stepped range a-bxN",
            )
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        step = int(match.group(3)) if match.group(3) is not None else 1
        for value in (first, last):
            if abs(value) > MAX_FRAME:
                raise SettingsError(field, f"{field}: frame {value} is beyond +-{MAX_FRAME}")
        if last < first:
            raise SettingsError(field, f"{field}: the range {part} is empty (its end is first)")
        if step < 1:
            raise SettingsError(field, f"{field}: the step of {part} must be at least 1")
        too_many = f"{field} names more than {max_frames} frames (the server's limit)"
        if (last - first) // step + 1 > max_frames:  # refused before any set is built
            raise SettingsError(field, too_many)
        frames.update(range(first, last + 1, step))
        if len(frames) > max_frames:
            raise SettingsError(field, too_many)
    return tuple(sorted(frames))


def frame_time(frame: int, fps: float) -> float:
    """The glTF time of a frame, in seconds: frame / fps (frame 1 is 1/24 s at 24 fps)."""
    return frame / fps


@functools.lru_cache(maxsize=256)
def _frames_of(text: str) -> tuple[int, ...]:
    return parse_frames(text, 2 * MAX_FRAME + 1)


ALL_VARIANTS = "all"  # settings.variant: every variant of the scene, one image each


def job_frames(settings: Any, variants: tuple[str, ...] = ()) -> tuple[int, ...] | None:
    """The numbers of a job's images, ascending: the frames of its (validated) settings, the
    indices of the scene's variants for a job that renders all of them (`variants`: their
    names, as stored with the job), None for a still."""
    if settings.frames:
        return _frames_of(settings.frames)
    return tuple(range(len(variants))) if variants else None


def frame_count(settings: Any, variants: tuple[str, ...] = ()) -> int:
    """How many images a job renders: its frames or variants, or 1 for a still."""
    frames = job_frames(settings, variants)
    return 1 if frames is None else len(frames)


def tiles_per_frame(settings: Any) -> int:
    return len(tile_grid(settings.width, settings.height, settings.tile_size))


def job_rects(settings: Any, variants: tuple[str, ...] = ()) -> list[Rect]:
    """The rect of every tile of a job, by tile index: frame slot s (its place in the frame
    list, or the variant's index) holds tiles s * tiles_per_frame ... (s + 1) * tiles_per_frame
    - 1, each frame's grid in row-major order (workers.proto, Task.tile_index)."""
    grid = tile_grid(settings.width, settings.height, settings.tile_size)
    return grid * frame_count(settings, variants)


def frame_slot(settings: Any, frame: int | None, variants: tuple[str, ...] = ()) -> int:
    """The slot of a frame number in a job's frame list (None: the still, or the first frame;
    a still's one image is also frame 0, as ListFrames numbers it; for a job of every variant,
    the variant's index); NotFound naming the field `frame` when the job does not render that
    frame."""
    frames = job_frames(settings, variants)
    if frame is None or (frames is None and frame == 0):  # a still's one image is frame 0
        return 0
    slot = bisect.bisect_left(frames, frame) if frames is not None else 0
    if frames is None or slot == len(frames) or frames[slot] != frame:
        if variants:
            rendered = f"it renders the variants 0..{len(variants) - 1} of its scene"
        else:
            rendered = (
                "it is a still, frame 0" if frames is None else f"its frames are {settings.frames}"
            )
        raise NotFound(f"the job does not render frame {frame}: {rendered}", "frame")
    return slot


def variant_file_names(names: tuple[str, ...] | list[str]) -> list[str]:
    """What to put in the file name of each variant's image, in order: its name with anything
    but letters, digits, '.', '_' and '-' made '_' ("Red", "Dark_blue"), or its index where
    that leaves nothing or repeats an earlier one ("2", and "3_Red" for a second "Red")."""
    out: list[str] = []
    for index, name in enumerate(names):
        safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")[:80]
        if not safe:
            safe = str(index)
        while safe in out:
            safe = f"{index}_{safe}"
        out.append(safe)
    return out


def check_animation_selection(
    text: str, field: str = "settings.animation"
) -> tuple[int | str, ...]:
    """The animations a job names: a comma list of indices (0, 2) and names ("Walk"), in the
    order given; () = all. SettingsError naming `field` for an empty item or a bad name."""
    if not text:
        return ()
    chosen: list[int | str] = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            raise SettingsError(field, f"{field} has an empty item: give indices or names, 0,Walk")
        if len(item) > 256 or any(ord(c) < 32 for c in item):
            raise SettingsError(field, f"{field}: {item[:40]!r} is not an animation index or name")
        chosen.append(int(item) if item.isdigit() else item)
    return tuple(chosen)


def resolve_animations(
    text: str, names: list[str] | tuple[str, ...], field: str = "settings.animation"
) -> tuple[int, ...]:
    """The indices of the animations a job names, checked against the scene's animations
    (their names in glTF order; an unnamed one is ""). () for all of them."""
    indices: list[int] = []
    for item in check_animation_selection(text, field):
        if isinstance(item, int):
            if item >= len(names):
                raise SettingsError(
                    field,
                    f"{field}: the scene has {len(names)} animation(s); there is no index {item}",
                )
            index = item
        elif item in names:
            index = names.index(item)
        else:
            known = ", ".join(repr(n) for n in names if n) or "none"
            raise SettingsError(
                field, f"{field}: the scene has no animation named {item!r} (named: {known})"
            )
        if index not in indices:
            indices.append(index)
    return tuple(indices)


def parse_shutter(text: str, field: str = "settings.shutter") -> tuple[float, float] | None:
    """The shutter interval of a motion-blurred frame: "OPEN,CLOSE", fractions of a frame from
    the frame's time (frame f opens at (f + OPEN) / fps); None for "" (closed: no motion blur).
    SettingsError naming `field` unless both are finite numbers with -1 <= OPEN < CLOSE <= 1
    and CLOSE - OPEN <= 1 (at most one frame)."""
    if not isinstance(text, str):
        raise SettingsError(field, f"{field} must be a string such as 0,0.5")
    if not text.strip():
        return None
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        opens, closes = (float(p) for p in parts)
    except ValueError:
        raise SettingsError(
            field,
            f"{field}: {text[:40]!r} is not OPEN,CLOSE: give the open and close times as "
            "fractions of a frame, 0,0.5 for a half-frame shutter",
        ) from None
    if not (-1.0 <= opens < closes <= 1.0 and closes - opens <= 1.0):
        raise SettingsError(
            field,
            f"{field}: {text[:40]!r}: the shutter must open before it closes, both within "
            "[-1, 1] frames of the frame's time and at most one frame apart",
        )
    return opens, closes

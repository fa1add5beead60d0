"""Frame lists (frames.parse_frames): the expected frames are written out by hand."""

from __future__ import annotations

import pytest

from renderfarm.domain.frames import frame_time, parse_frames
from renderfarm.domain.jobspec import SettingsError


@pytest.mark.parametrize(
    ("text", "frames"),
    [
        ("7", (7,)),
        ("1-5", (1, 2, 3, 4, 5)),
        ("1-10x3", (1, 4, 7, 10)),
        ("1-11x3", (1, 4, 7, 10)),
        ("1,5,10-12", (1, 5, 10, 11, 12)),
        ("10-12, 1, 5", (1, 5, 10, 11, 12)),  # ascending, spaces allowed
        ("3,1-4,3", (1, 2, 3, 4)),  # each frame once
        ("-3--1", (-3, -2, -1)),
        ("-2-1", (-2, -1, 0, 1)),
        ("0", (0,)),
        ("5-5x7", (5,)),
    ],
)
def test_frame_lists(text, frames):
    assert parse_frames(text, max_frames=1000) == frames


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty"),
        ("   ", "empty"),
        ("1-", "not a frame"),
        ("a-b", "not a frame"),
        ("1..5", "not a frame"),
        ("1,,2", "not a frame"),
        ("1-5x", "not a frame"),
        ("5-1", "empty"),
        ("1-5x0", "step"),
        ("1-2000000", "beyond"),
        ("1-1001", "more than 1000"),
        ("1-600,601-1001", "more than 1000"),
    ],
)
def test_bad_lists_name_the_setting(text, message):
    with pytest.raises(SettingsError) as refused:
        parse_frames(text, max_frames=1000)
    assert refused.value.field == "settings.frames" and message in str(refused.value)


def test_the_limit_counts_frames_not_list_items():
    assert len(parse_frames("1-1000,1-1000", max_frames=1000)) == 1000


def test_frame_time_is_the_exporters_mapping():
    assert frame_time(1, 24.0) == 1 / 24 and frame_time(48, 24.0) == 2.0
    assert frame_time(0, 30.0) == 0.0 and frame_time(-12, 24.0) == -0.5

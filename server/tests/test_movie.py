"""Preview movies' encoder (infra/movie.py): what a missing or failing ffmpeg becomes."""

from __future__ import annotations

import asyncio

import pytest

from renderfarm.infra import movie


def test_a_missing_ffmpeg_says_how_to_install_it(monkeypatch):
    monkeypatch.setenv("PATH", "/nonexistent")
    with pytest.raises(movie.EncoderMissing, match="apt install ffmpeg"):
        movie.find_ffmpeg()


def test_a_failing_ffmpeg_is_a_movie_error_and_leaves_no_file(tmp_path):
    out = tmp_path / "m.mp4"
    with pytest.raises(movie.MovieError, match="ffmpeg failed"):  # no frames to read
        asyncio.run(movie.encode_mp4(tmp_path, "f%06d.png", 24.0, out, 60.0))
    assert not out.exists() and not (tmp_path / "m.mp4.partial").exists()

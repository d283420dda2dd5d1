"""Orbit animations: GIF or MP4 chosen by the file name."""

from __future__ import annotations

import importlib.util

import imageio.v3 as iio
import numpy as np
import pytest

from diamond_sss.evaluation import run as run_module
from diamond_sss.evaluation.run import check_animation_path, write_animation


def frames(count: int = 3, height: int = 9, width: int = 7) -> list[np.ndarray]:
    return [np.full((height, width, 3), 40 * k, np.uint8) for k in range(count)]


def test_gif_round_trip(tmp_path):
    path = write_animation(tmp_path / "orbit.gif", frames())
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (3, 9, 7) and [int(f[..., 0].mean()) for f in back] == [0, 40, 80]


def test_unknown_suffix_and_missing_mp4_writer_are_refused(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"--video .*orbit\.avi: expected a file name ending in \.gif or \.mp4"):
        check_animation_path(tmp_path / "orbit.avi")
    monkeypatch.setattr(run_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError, match="writing MP4 needs imageio-ffmpeg"):
        write_animation(tmp_path / "orbit.mp4", frames())
    assert check_animation_path(tmp_path / "ORBIT.GIF") == ".gif"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="imageio-ffmpeg not installed")
def test_mp4_has_every_frame_at_even_size(tmp_path):
    path = write_animation(tmp_path / "orbit.mp4", frames(count=5))
    assert path.read_bytes()[4:8] == b"ftyp"
    back = iio.imread(path, index=None, plugin="FFMPEG")
    assert back.shape[:3] == (5, 10, 8)

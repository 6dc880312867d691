"""Videos of any frame size keep their pixels: padded to x264's multiple of 8, never rescaled."""

from __future__ import annotations

import logging

import imageio.v3 as iio
import numpy as np

from so101_sim.harness.video import EpisodeVideo


def _no_rescale_warning(caplog) -> None:
    said = [r.getMessage() for r in caplog.records if "macro_block_size" in r.getMessage()]
    assert not said, said


def test_an_episode_video_of_odd_height_is_padded_not_stretched(tmp_path, caplog):
    """61 rows are enlarged 4x to 244 for the label; imageio used to rescale that to 248."""
    caplog.set_level(logging.WARNING)
    rng = np.random.default_rng(0)
    frame = np.zeros((61, 160, 3), np.uint8)
    frame[30:, :80] = 200  # a bright block down to the frame's last row
    frame[:, 80:] = rng.integers(0, 255, (61, 80, 3), dtype=np.uint8)
    video = EpisodeVideo(tmp_path / "ep.mp4", fps=30, seed=7)
    for step in range(5):
        video.add(frame, step)
    path = video.finish("success", 5)
    frames = iio.imread(path, plugin="pyav")
    _no_rescale_warning(caplog)
    assert frames.shape[1:] == (248, 640, 3)
    last = frames[-1].astype(int)
    # The block keeps its 4x enlarged extent: rows 120..243 bright, 244..247 the black pad.
    assert last[130:240, 10:300].mean() > 180
    assert last[245:, :].mean() < 20
    assert last[110:118, 10:300].mean() < 20  # above the block stays dark: nothing smeared


def test_the_demo_at_84x84_keeps_every_pixel_of_the_render(tmp_path, caplog):
    from so101_sim.cli import main

    caplog.set_level(logging.WARNING)
    assert main(["demo", "--steps", "6", "--image-size", "84x84", "--out", str(tmp_path)]) == 0
    _no_rescale_warning(caplog)
    frames = iio.imread(tmp_path / "demo.mp4", plugin="pyav")
    assert frames.shape == (7, 88, 168, 3)  # front|side 84x168, four black rows below
    assert frames[-1, 84:].max() < 24
    front = iio.imread(tmp_path / "front.png").astype(int)
    # the video's last frame is that render, lossily coded but in place
    assert np.abs(frames[-1, :84, :84].astype(int) - front).mean() < 4

"""H.264 mp4 files for the demo and the harness's episode videos.

libx264's 4:2:0 frames, and many players, want each side a multiple of 8 pixels. Given
another size, imageio has ffmpeg rescale every frame (a blurred, slightly stretched copy) and
logs a two-line warning per file; an 84x84 or 61x80 render gets that. Frames are padded with
black along the bottom and right edges instead, so each pixel stays where it was drawn.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np

BLOCK = 8  # the side multiple asked of every frame


def pad_to_block(frame: np.ndarray) -> np.ndarray:
    """`frame` (H, W, 3) with black rows and columns added until both sides divide by 8."""
    h, w = frame.shape[:2]
    dh, dw = -h % BLOCK, -w % BLOCK
    if not (dh or dw):
        return frame
    return np.pad(frame, ((0, dh), (0, dw), (0, 0)))


class H264Writer:
    """Streams frames into an mp4 at `path`; x264 `preset` None is libx264's default."""

    def __init__(self, path: str | Path, fps: int, preset: str | None = None) -> None:
        self._writer = imageio.get_writer(
            path, fps=fps, codec="libx264", quality=7, macro_block_size=BLOCK,
            ffmpeg_params=["-preset", preset] if preset else None)

    def append(self, frame: np.ndarray) -> None:
        self._writer.append_data(pad_to_block(frame))

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> H264Writer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Episode videos: front|side side by side with the step and, at the end, the outcome drawn on.

Encoded inside the env worker, frame by frame, so no raw frames cross process (or machine)
boundaries: the worker hands the finished mp4's bytes back with the episode's last reply and
the driver writes it under its final name. A worker that dies leaves no half-written video in
the evaluation folder.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from so101_sim.utils.mp4 import H264Writer

MIN_HEIGHT = 240  # small renders are enlarged (nearest) so the text stays readable
HOLD_S = 1.0  # the last frame, with the outcome, is held this long


class EpisodeVideo:
    """Streams one episode to ``path`` (mp4, H.264)."""

    def __init__(self, path: str | Path, fps: int, seed: int) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.stem + ".part.mp4")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps, self.seed = fps, seed
        # x264 "veryfast": half the encoding CPU of the default preset, in the worker's time.
        self._writer = H264Writer(self.tmp, fps, preset="veryfast")
        self._last: np.ndarray | None = None

    def add(self, frame: np.ndarray, step: int) -> None:
        """Append a rendered front|side frame taken after `step` actions."""
        self._last = _enlarge(frame)
        self._writer.append(_label(self._last, f"seed {self.seed}  step {step}"))

    def finish(self, outcome: str, steps: int) -> Path:
        """Hold the last frame with the outcome, close the file and give it its final name."""
        if self._last is not None:
            good = outcome == "success"
            text = f"seed {self.seed}  step {steps}  {outcome.upper()}"
            frame = _label(self._last, text, (40, 170, 40) if good else (200, 40, 40))
            for _ in range(max(1, round(HOLD_S * self.fps))):
                self._writer.append(frame)
        self._writer.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        self._writer.close()
        self.tmp.unlink(missing_ok=True)


def _enlarge(frame: np.ndarray) -> np.ndarray:
    h = frame.shape[0]
    if h >= MIN_HEIGHT:
        return frame
    k = -(-MIN_HEIGHT // h)
    return cv2.resize(frame, (frame.shape[1] * k, h * k), interpolation=cv2.INTER_NEAREST)


def _label(frame: np.ndarray, text: str,
           colour: tuple[int, int, int] = (30, 30, 30)) -> np.ndarray:
    """A copy of `frame` with `text` in white on a coloured bar along the top."""
    out = frame.copy()
    scale = max(0.7, frame.shape[0] / 480)
    bar = int(22 * scale) + 6
    out[:bar] = (0.35 * out[:bar] + 0.65 * np.array(colour)).astype(np.uint8)
    cv2.putText(out, text, (6, bar - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                (255, 255, 255), max(1, int(scale + 0.5)), cv2.LINE_AA)
    return out

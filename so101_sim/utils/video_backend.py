"""One line instead of lerobot's ~100-line torchcodec traceback on machines without FFmpeg.

lerobot 0.6 picks its video decoder in ``get_safe_default_video_backend``: it imports
torchcodec and, when that fails, logs the loader's whole traceback (one try per FFmpeg major
version) as a warning and then uses PyAV. torchcodec needs FFmpeg 4-8 *shared* libraries,
which pip cannot install, so on such a machine every command that opens a dataset (record,
train, lerobot-eval, the tests) starts with what reads like a crash. PyAV is lerobot's own
fallback and decodes the same frames, so ``import so101_sim`` adds a filter to that logger:
when no FFmpeg shared library can be loaded, the warning is replaced by one line, once per
process tree. When FFmpeg is there and torchcodec still fails, lerobot's warning is kept: the
reason is then something else, and its traceback is the useful part.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys

LEROBOT_LOGGER = "lerobot.utils.import_utils"
NOTED_ENV = "SO101_SIM_PYAV_NOTED"  # set once the line is printed; child processes inherit it
# libavutil's soname major per FFmpeg release that torchcodec supports: 4.x .. 8.x
AVUTIL_MAJORS = {4: 56, 5: 57, 6: 58, 7: 59, 8: 60}
NOTE = ("so101-sim: torchcodec cannot load (no FFmpeg 4-8 shared libraries found); lerobot "
        "decodes videos with PyAV instead. To use torchcodec, install FFmpeg's shared libraries, "
        "e.g. `apt-get install ffmpeg`")


def ffmpeg_shared_version() -> int | None:
    """FFmpeg major version whose libavutil the dynamic loader finds (as torchcodec would)."""
    for version, major in sorted(AVUTIL_MAJORS.items(), reverse=True):
        try:
            ctypes.CDLL(f"libavutil.so.{major}")
        except OSError:
            continue
        return version
    return None


class PyAVFallbackNote(logging.Filter):
    """Replaces lerobot's torchcodec fallback warning by `NOTE` when FFmpeg is missing."""

    def __init__(self) -> None:
        super().__init__()
        self.checked = False
        self.ffmpeg: int | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        if record.funcName != "get_safe_default_video_backend":
            return True
        if not self.checked:  # once per process, on lerobot's first fallback
            self.ffmpeg, self.checked = ffmpeg_shared_version(), True
        if self.ffmpeg is not None:
            return True  # FFmpeg is there: the failure has another cause; show lerobot's words
        if not os.environ.get(NOTED_ENV):
            os.environ[NOTED_ENV] = "1"
            print(NOTE, file=sys.stderr)
        return False


def quiet_pyav_fallback() -> None:
    """Install the filter on lerobot's logger (idempotent; does not import lerobot)."""
    logger = logging.getLogger(LEROBOT_LOGGER)
    if not any(isinstance(f, PyAVFallbackNote) for f in logger.filters):
        logger.addFilter(PyAVFallbackNote())


def quiet_libav() -> None:
    """Hide libav's info chatter (x264's per-file statistics, remux notes) on the console."""
    import av

    av.logging.set_libav_level(av.logging.WARNING)

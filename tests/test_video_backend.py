"""A quiet start: one line, not lerobot's torchcodec traceback, when FFmpeg is missing."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest

from so101_sim.utils import video_backend

CHECK = ("import so101_sim, subprocess, sys; "
         "from lerobot.utils.import_utils import get_safe_default_video_backend as pick; "
         "print(pick(), pick()); sys.stdout.flush(); "
         "subprocess.run([sys.executable, '-c', 'import so101_sim; "
         "from lerobot.utils.import_utils import get_safe_default_video_backend as p; "
         "print(p())'], check=True)")


def test_lerobot_falls_back_to_pyav_with_one_line():
    env = {k: v for k, v in os.environ.items() if k != video_backend.NOTED_ENV}
    run = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True,
                         timeout=300, env=env, check=True)
    if video_backend.ffmpeg_shared_version() is not None:
        assert run.stdout.split() == ["torchcodec"] * 3 and not run.stderr.strip()
        return
    # No FFmpeg here: lerobot chose PyAV three times (twice in this process, once in a
    # child), and all it printed is our one line.
    assert run.stdout.split() == ["pyav"] * 3
    assert run.stderr.strip().splitlines() == [video_backend.NOTE]


@pytest.mark.parametrize(("ffmpeg", "shown"), [(None, False), (7, True)])
def test_filter_keeps_other_failures_visible(monkeypatch, capsys, ffmpeg, shown):
    monkeypatch.delenv(video_backend.NOTED_ENV, raising=False)
    monkeypatch.setattr(video_backend, "ffmpeg_shared_version", lambda: ffmpeg)
    note = video_backend.PyAVFallbackNote()
    record = logging.LogRecord(video_backend.LEROBOT_LOGGER, logging.WARNING, "x.py", 1,
                               "Could not load libtorchcodec ...", None, None,
                               func="get_safe_default_video_backend")
    assert note.filter(record) is shown and note.filter(record) is shown
    err = capsys.readouterr().err
    assert err.count("torchcodec cannot load") == (0 if shown else 1)  # once, not per call
    other = logging.LogRecord("x", logging.WARNING, "x.py", 1, "other", None, None, func="f")
    assert note.filter(other)

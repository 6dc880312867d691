"""The dataset's schema: features, cameras, codecs and the seed rule every writer follows.

``record`` and ``eval --save-rollouts`` write LeRobotDatasets with these features (lerobot's
SO-101 follower conventions: ``observation.state`` and ``action`` in LeRobot units, the
cameras as video, fps 30) plus each episode's reset seed and initial cube pose, so any
episode can be re-simulated.
"""

from __future__ import annotations

from typing import Any

from so101_sim.tasks import DEFAULT_CAMERAS
from so101_sim.utils.numbers import check_count
from so101_sim.utils.text import seed_span
from so101_sim.utils.units import FEATURE_NAMES

#: Demonstrations come from the training seed range; seeds >= this are for evaluation only.
EVAL_SEED_START = 100_000
DEFAULT_REPO_ID = "local/so101_pick_place"
ROBOT_TYPE = "so101_follower"
CAMERAS = DEFAULT_CAMERAS
VIDEO_KEYS = tuple(f"observation.images.{cam}" for cam in CAMERAS)
#: Video codecs `record` offers. h264 (libx264 "veryfast", crf 23) costs about half the CPU of
#: lerobot's default AV1 (libsvtav1 preset 12, crf 30) per 480x640 frame at a similar file size
#: and PSNR, and decodes ~3x faster; that is what lets two cores record >= 50 env-steps/s.
VCODECS: dict[str, dict[str, Any]] = {
    "h264": {"vcodec": "h264", "preset": "veryfast", "crf": 23},
    "libsvtav1": {"vcodec": "libsvtav1"},
}
DEFAULT_VCODEC = "h264"


def dataset_features(image_size: tuple[int, int], dart: bool = False,
                     cameras: tuple[str, ...] = CAMERAS) -> dict[str, dict[str, Any]]:
    """lerobot feature spec: state/action, the cameras as video, and the re-simulation extras
    (``action_executed`` with DART noise)."""
    h, w = image_size
    names = list(FEATURE_NAMES)
    feats: dict[str, dict[str, Any]] = {
        "observation.state": {"dtype": "float32", "shape": (6,), "names": names},
        "action": {"dtype": "float32", "shape": (6,), "names": names},
    }
    for cam in cameras:
        feats[f"observation.images.{cam}"] = {"dtype": "video", "shape": (h, w, 3),
                      "names": ["height", "width", "channels"]}
    feats["episode_seed"] = {"dtype": "int64", "shape": (1,), "names": None}
    feats["initial_cube_pose"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "yaw_deg"]}
    if dart:
        feats["action_executed"] = {"dtype": "float32", "shape": (6,), "names": names}
    return feats


def check_video_size(image_size: tuple[int, int], what: str) -> None:
    """Refuse a frame size the video encoders cannot open (libx264 and SVT-AV1 store 4:2:0
    frames, which need even sides), before a dataset is created: lerobot's encoder thread
    would otherwise crash on the first episode."""
    h, w = image_size
    if h % 2 or w % 2:
        even = f"{h - h % 2}x{w - w % 2}"
        raise ValueError(f"{what} {h}x{w} has an odd side; a dataset stores each camera as "
                         "4:2:0 video (H.264 or AV1), whose frames need even sides: use "
                         f"{even}, e.g. --image-size {even}")


def check_seed_range(seed_start: int, n_seeds: int = 1) -> None:
    """Refuse evaluation seeds: demos trained on them would leak into the benchmark."""
    check_count("seed_start", seed_start, 0, f"demo seeds are 0..{EVAL_SEED_START - 1}")
    if seed_start + n_seeds > EVAL_SEED_START:
        fix = (f"; {n_seeds} episodes fit with --seed-start {EVAL_SEED_START - n_seeds} or lower"
               if n_seeds > 1 and seed_start < EVAL_SEED_START else "")
        raise ValueError(
            f"{seed_span(seed_start, seed_start + n_seeds - 1)} "
            f"{'reaches' if n_seeds == 1 else 'reach'} the evaluation range "
            f"(>= {EVAL_SEED_START}); demonstrations must use training seeds "
            f"0..{EVAL_SEED_START - 1}{fix}")


def rollout_features(image_size: tuple[int, int], cameras: tuple[str, ...]
                     ) -> dict[str, dict[str, Any]]:
    """``eval --save-rollouts``: the recording features plus reward, success and done per frame
    and each episode's outcome."""
    one = {"shape": (1,), "names": None}
    feats = dataset_features(image_size, cameras=cameras)
    feats["next.reward"] = {"dtype": "float32", **one}
    feats["next.success"] = {"dtype": "bool", **one}
    feats["next.done"] = {"dtype": "bool", **one}
    feats["episode_success"] = {"dtype": "bool", **one}
    feats["episode_failure_mode"] = {"dtype": "string", **one}
    return feats

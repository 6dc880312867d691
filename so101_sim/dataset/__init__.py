"""Datasets: the LeRobotDataset schema every writer follows, the kill-safe writer (spool,
checkpoints, recovery) and the readers. ``record`` and ``eval --save-rollouts`` write through
here; ``train`` and ``explain`` read through ``open_lerobot_dataset``."""

from so101_sim.dataset.reader import (
    NotADatasetError,
    info_features,
    open_lerobot_dataset,
    read_frames,
    recorded_seeds,
    recorded_task,
    stored_seeds,
)
from so101_sim.dataset.robot_episodes import (
    ROBOT_EPISODES,
    append_robot_episode,
    noted_seeds,
    noted_task,
    read_robot_episodes,
)
from so101_sim.dataset.schema import (
    CAMERAS,
    DEFAULT_REPO_ID,
    DEFAULT_VCODEC,
    EVAL_SEED_START,
    ROBOT_TYPE,
    VCODECS,
    VIDEO_KEYS,
    check_seed_range,
    check_video_size,
    dataset_features,
)
from so101_sim.dataset.store import SIDECAR, read_sidecar

__all__ = ["CAMERAS", "DEFAULT_REPO_ID", "DEFAULT_VCODEC", "EVAL_SEED_START", "ROBOT_EPISODES",
           "ROBOT_TYPE", "SIDECAR", "VCODECS", "VIDEO_KEYS", "NotADatasetError",
           "append_robot_episode", "check_seed_range", "check_video_size", "dataset_features",
           "info_features", "noted_seeds", "noted_task", "open_lerobot_dataset", "read_frames",
           "read_robot_episodes", "read_sidecar", "recorded_seeds", "recorded_task",
           "stored_seeds"]

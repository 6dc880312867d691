"""Deprecated: recording moved to ``so101_sim.record`` and ``so101_sim.dataset`` (kept for one
release; import from there)."""

import warnings

from so101_sim.dataset import (
    CAMERAS,
    DEFAULT_REPO_ID,
    EVAL_SEED_START,
    ROBOT_TYPE,
    SIDECAR,
    VIDEO_KEYS,
    check_seed_range,
    dataset_features,
    stored_seeds,
)
from so101_sim.record import check_dart_noise, expert_options, record, replay, run_episode

warnings.warn("so101_sim.recording is deprecated and will be removed in the next release; "
              "import record/replay from so101_sim.record and the dataset schema from "
              "so101_sim.dataset", DeprecationWarning, stacklevel=2)

__all__ = ["CAMERAS", "DEFAULT_REPO_ID", "EVAL_SEED_START", "ROBOT_TYPE", "SIDECAR", "VIDEO_KEYS",
           "check_dart_noise", "check_seed_range", "dataset_features", "expert_options",
           "record", "replay", "run_episode", "stored_seeds"]

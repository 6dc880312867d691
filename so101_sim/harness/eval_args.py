"""Argument checks of ``evaluate``: each error names the value, what was expected and, for a
training seed, the flag that allows it."""

from __future__ import annotations

from typing import Any

from so101_sim.dataset import EVAL_SEED_START
from so101_sim.sim.env_args import check_image_size
from so101_sim.utils.numbers import check_count, check_seconds

__all__ = ["check_eval_args"]


def check_eval_args(*, episodes: Any, n_envs: Any, seed_start: Any, videos: Any,
                    allow_train_seeds: bool, image_size: Any = None, threads: Any = None,
                    worker_timeout_s: Any = 600.0, max_retries: Any = 2,
                    checkpoint_every: Any = 50) -> None:
    check_count("episodes", episodes, 1, "seeds to evaluate")
    check_count("n_envs", n_envs, 1, "env workers")
    check_count("videos", videos, 0, "episodes to film")
    check_count("seed_start", seed_start, 0, "the first seed")
    if threads is not None:
        check_count("threads", threads, 1, "torch threads; None for half the cores")
    check_count("max_retries", max_retries, 0, "reruns of an episode whose worker died")
    check_count("checkpoint_every", checkpoint_every, 1, "episodes between dataset checkpoints")
    check_seconds("worker_timeout_s", worker_timeout_s)
    if image_size is not None:
        check_image_size(image_size)
    if seed_start < EVAL_SEED_START and not allow_train_seeds:
        raise ValueError(f"seed_start={seed_start} is a training seed (demos use seeds below "
                         f"{EVAL_SEED_START}); evaluate on seeds >= {EVAL_SEED_START}, or pass "
                         "--allow-train-seeds to measure on training seeds on purpose")

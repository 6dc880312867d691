"""Train: lerobot's DiffusionPolicy (or ACT) on a recorded dataset, fast on a CPU
(``so101-sim train``).

``trainer.train`` (frames decoded once by ``frame_cache``, optionally jittered by ``augment``,
EMA weights, resumable state in ``state``, thread control in ``threads``) from a preset
(``presets``: ``policy/presets/*.toml``); ``checkpoint`` is the one reader of the folders it
writes. torch loads on first use.
"""

from typing import Any

from so101_sim.train.checkpoint import TRAIN_INFO, load_checkpoint, read_train_info

__all__ = ["TRAIN_INFO", "TrainError", "load_checkpoint", "read_train_info", "train"]


def __getattr__(name: str) -> Any:
    if name in ("train", "TrainError"):
        from so101_sim.train import trainer

        return getattr(trainer, name)
    raise AttributeError(f"module 'so101_sim.train' has no attribute {name!r}")

"""A training run folder's state on disk: finding checkpoints, reading them safely, and the
checks a resume makes before it continues (same architecture, a clean log).

`training_state.pt` holds tensors and plain values only and is read with
``torch.load(weights_only=True)``: a crafted file from someone else cannot run code.
"""

from __future__ import annotations

import copy
import json
import math
import pickle
import shutil
from pathlib import Path
from shlex import quote
from typing import Any

import torch

from so101_sim.train.checkpoint import TRAIN_INFO, read_train_info
from so101_sim.train.presets import Preset
from so101_sim.utils.atomic import write_text_atomic
from so101_sim.utils.numbers import check_count
from so101_sim.utils.versions import setup_differences


class TrainError(RuntimeError):
    """Bad training input (dataset, preset, run folder)."""


def check_counts(**counts: Any) -> None:
    """Each count given (not None) an integer >= 1, else a TrainError naming it: the Python
    API's `steps=2.5` trained 2 steps and `threads=0` meant "adaptive" in silence."""
    for name, value in counts.items():
        if value is not None:
            try:
                check_count(name, value, 1)
            except ValueError as exc:
                raise TrainError(str(exc)) from None


class TrainingStopped(KeyboardInterrupt):
    """A signal stopped the training loop; its message names the step and the checkpoint."""


def save_ema_policy(policy: Any, ema: Any, pre: Any, post: Any, dest: Path,
                    info: dict[str, Any]) -> None:
    """EMA weights in lerobot's pretrained format, written whole (a temporary folder renamed)."""
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shadow = copy.deepcopy(policy)
    ema.copy_to(shadow.parameters())
    shadow.save_pretrained(tmp)
    pre.save_pretrained(tmp)
    post.save_pretrained(tmp)
    (tmp / TRAIN_INFO).write_text(json.dumps(info, indent=2) + "\n")
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)


def discard_partial_checkpoint(ck: Path) -> None:
    """After a failed save (a full disk): free what it wrote. A folder without its
    training_state.pt is no checkpoint, so the previous one stays the one --resume uses."""
    shutil.rmtree(ck / "pretrained_model.tmp", ignore_errors=True)
    (ck / "training_state.tmp").unlink(missing_ok=True)
    if not (ck / "training_state.pt").exists():
        shutil.rmtree(ck, ignore_errors=True)


def copy_policy(src: Path, dest: Path) -> None:
    """Copy a pretrained_model folder to `dest`, replacing it only once the copy is whole."""
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(src, tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)


def list_checkpoints(out: Path) -> list[Path]:
    return sorted(p.parent for p in (out / "checkpoints").glob("step_*/training_state.pt"))


def architecture(preset: Preset) -> dict[str, Any]:
    """What a preset fixes about the model: its config's fields and image size (and the policy
    type where it is not diffusion, and the augmentation where there is one, so runs from before
    those existed compare equal)."""
    arch = json.loads(json.dumps(preset.policy, default=str))
    arch["image_size"] = list(preset.image_size)
    if preset.policy_type != "diffusion":
        arch["policy_type"] = preset.policy_type
    if preset.augment is not None:  # the recipe's frames; runs without it compare as before
        arch["augment"] = json.loads(json.dumps(preset.augment))
    return arch


def check_same_architecture(state: dict[str, Any], preset: Preset, out: Path) -> None:
    old = state.get("preset_arch")
    if old is None:
        return  # older run: load_state_dict reports a mismatch
    new = architecture(preset)
    changed = sorted(k for k in old.keys() | new.keys()
                     if k not in ("device",) and old.get(k) != new.get(k))
    if changed:
        diff = "; ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in changed[:6])
        raise TrainError(f"{out} was started with preset {preset.name!r} as it was then, and "
                         f"{preset.path} differs now ({diff}); resume with the original preset "
                         "file, or start a new --out for the new settings")


def load_training_state(path: Path, device: str) -> dict[str, Any]:
    """A checkpoint's training state, unpickled with weights_only=True (no code can run)."""
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as e:
        raise TrainError(f"{path} holds objects other than tensors and plain values, so it is "
                         f"not loaded (that could run code): {str(e).splitlines()[0]}. Such a "
                         "run folder (older, or made elsewhere) cannot be resumed; start a new "
                         "--out (its pretrained_model/ still evaluates)"
                         ) from None
    except (RuntimeError, EOFError, OSError) as e:
        raise TrainError(f"{path} cannot be read ({e}); delete that checkpoint folder to "
                         "resume from the one before it") from None


def truncate_log(path: Path, step: int) -> None:
    """Drop log lines past `step` (written after the checkpoint a resume starts from) and a
    torn line a kill left mid-write, so the next record starts on a line of its own."""
    if not path.is_file():
        return
    keep = []
    for n, ln in enumerate(path.read_text().splitlines(), 1):
        try:
            rec = json.loads(ln)
        except json.JSONDecodeError:
            print(f"so101-sim train: {path}: dropped unreadable line {n} (cut by a kill?)")
            continue
        if isinstance(rec, dict) and rec.get("step", math.inf) <= step:
            keep.append(ln)
    write_text_atomic(path, "".join(ln + "\n" for ln in keep))


def own_info(last: Path) -> dict[str, Any]:
    """The sidecar of a run's last checkpoint ({} if torn by a kill or missing)."""
    try:
        return read_train_info(last / "pretrained_model") or {}
    except ValueError:
        return {}


def check_same_dataset(last: Path, dataset: Any, dataset_dir: Path, out: Path) -> None:
    """A resumed run draws from the frames it started on: a dataset that grew or shrank since
    (e.g. `record --resume` into it) would make it another run, in silence."""
    info, meta = own_info(last), dataset.meta
    if info.get("dataset_frames") not in (None, meta.total_frames):
        raise TrainError(f"{out} was trained on {info.get('dataset_episodes')} episodes "
                         f"({info['dataset_frames']} frames) of {dataset_dir}, which now holds "
                         f"{meta.total_episodes} ({meta.total_frames} frames); a resume would "
                         "not be the same run: fine-tune on it in a new run with --init-from "
                         f"{last / 'pretrained_model'}")


def resumed_sizes(last: Path, steps: int | None, batch_size: int | None,
                  out: Path) -> tuple[int | None, int | None]:
    """A resumed run's total steps and batch size: its own where not given (a resume that
    left out `--steps 40000` used to fall back to the preset's and end early). Another batch
    size, or fewer total steps than are done, is refused."""
    info = own_info(last)
    own_batch, done = info.get("batch_size"), info.get("step")
    if batch_size is None:
        batch_size = own_batch
    elif own_batch is not None and batch_size != own_batch:
        raise TrainError(f"{out} was trained at --batch-size {own_batch}, not {batch_size}; "
                         "resume without --batch-size (a run keeps one), or fine-tune at "
                         "another in a new run with --init-from "
                         f"{quote(str(last / 'pretrained_model'))}")
    steps = info.get("total_steps") if steps is None else steps
    if steps is not None and done is not None and steps < done:
        raise TrainError(f"--steps {steps}: {out} is already at step {done}; give more total "
                         "steps to continue it, or leave --steps out to finish its own")
    return steps, batch_size


def joined_setups(history: Any, step: int, setup: dict[str, Any]
                  ) -> tuple[list[list[Any]], list[str]]:
    """The run's ``[first step, setup]`` stretches with `setup` from `step` on, and how it
    differs from the last one (``utils.versions.setup_differences``; [] when it does not):
    a resume on other software or another CPU is not bitwise the uninterrupted run."""
    kept = [h for h in history if isinstance(h, list) and len(h) == 2
            and isinstance(h[1], dict)] if isinstance(history, list) else []
    differ = setup_differences(kept[-1][1], setup) if kept else []
    return (kept if kept and not differ else [*kept, [step, setup]]), differ

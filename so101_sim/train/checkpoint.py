"""Checkpoints: lerobot's pretrained-policy folders as ``train`` writes and everything loads them.

A checkpoint is ``config.json`` + ``model.safetensors`` + the saved pre/post-processor
pipelines, plus our sidecar ``so101_sim_train.json`` (preset, step, the image sizes training
recorded and used). One loader for all readers (the harness, ``explain``, ``curve``,
``export``): files are checked first, processor files that would import code are refused
(``utils.trust``), then lerobot's own factory builds the policy. torch loads on first use.
"""

from __future__ import annotations

import contextlib
import io
import json
import warnings
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.dataset.reader import recorded_seeds, recorded_task
from so101_sim.dataset.schema import EVAL_SEED_START
from so101_sim.tasks import available_tasks, load_task
from so101_sim.train.presets import config_class
from so101_sim.train.widen import widen_conditioning, widen_keypoints
from so101_sim.utils.paths import hub_id_hint, policy_dir
from so101_sim.utils.text import counted
from so101_sim.utils.trust import check_processor_files

#: The sidecar ``train`` writes beside each checkpoint's weights.
TRAIN_INFO = "so101_sim_train.json"
#: Its keys for what the demos were of: the recording's task (a name, or a .toml path; null for
#: a dataset ``record`` did not write, e.g. a merge of several), every task text in them, and
#: the evaluation seeds among theirs as [first, last] ranges (rollouts of ``eval
#: --save-rollouts``: the harness will not measure the policy on its own training episodes).
TASK_KEY, TEXTS_KEY, SEEDS_KEY = "dataset_task", "dataset_task_texts", "dataset_eval_seeds"
#: lerobot-train's record of its command line, beside each checkpoint's weights.
LEROBOT_TRAIN_CONFIG = "train_config.json"
#: lerobot's key prefix of a camera's image input (``observation.images.<camera>``).
IMAGE_PREFIX = "observation.images."


def nearby_policies(path: Path) -> list[Path]:
    """Policy folders a user who typed `path` likely meant: the `pretrained_model` inside it (a
    run or a step folder given), or, for a path that does not exist, the final and the latest
    checkpointed policy of the nearest training run above it (`train` keeps
    ``checkpoints/step_NNNNNNN``, with no ``last`` link as lerobot-train makes). A
    lerobot-train run folder given names its ``checkpoints/last/pretrained_model``; a folder
    of policies (``policy/``), the policies in it."""
    for inside in ("pretrained_model", "checkpoints/last/pretrained_model"):
        if (path / inside / "config.json").is_file():
            return [path / inside]
    if path.is_dir():
        return sorted(p for p in path.iterdir() if (p / "config.json").is_file())[:3]
    if path.exists():
        return []
    existing = next((p for p in path.parents if p.is_dir()), None)
    if existing is None:
        return []
    for run in (existing, *existing.parents)[:4]:
        steps = sorted(run.glob("checkpoints/step_*/pretrained_model/config.json"))
        found = [p.parent for p in (run / "pretrained_model" / "config.json", *steps[-1:])
                 if p.is_file()]
        if found:
            return found
    return []


def shipped_named(path: Path) -> list[Path]:
    """The shipped policy a relative path that is not there names by its last part, as
    ``policy/pick_place_diffusion`` typed outside the checkout (or the wheel's data)."""
    if path.is_absolute() or path.exists():
        return []
    try:
        shipped = policy_dir() / path.name
    except FileNotFoundError:  # an incomplete install; the caller's own error says enough
        return []
    return [shipped] if (shipped / "config.json").is_file() else []


def check_files(path: Path, flag: str = "--policy") -> None:
    """A checkpoint folder has lerobot's four files, else FileNotFoundError; `flag` is how the
    user passed it, for the suggestions."""
    if not path.is_dir():
        raise FileNotFoundError(f"policy checkpoint {path} not found; {_files_hint(path, flag)}")
    for name in ("config.json", "model.safetensors", "policy_preprocessor.json",
                 "policy_postprocessor.json"):
        if not (path / name).is_file():
            raise FileNotFoundError(f"policy checkpoint {path} has no {name}; "
                                    f"{_files_hint(path, flag)}")


def _files_hint(path: Path, flag: str) -> str:
    """What to pass instead of `path`; only built on a failed check (it searches nearby)."""
    hint = ("expected a lerobot checkpoint directory with config.json, model.safetensors and "
            "policy_preprocessor.json/policy_postprocessor.json (so101-sim train writes the "
            "final one to RUN/pretrained_model, lerobot-train to "
            "outputs/train/<run>/checkpoints/<step>/pretrained_model)"
            + (", or --policy expert" if flag == "--policy" else ""))
    near = nearby_policies(path) or shipped_named(path)
    if near:  # in a folder holding a run, USER/REPO still gets how to fetch it
        return (f"did you mean {flag} {f' or {flag} '.join(map(str, near))}? " + hint
                + hub_id_hint(path, flag))
    return other_kind(path) + hint + hub_id_hint(path, flag)


def other_kind(path: Path) -> str:
    """What a folder given for a policy is instead, if so101-sim wrote it ("" if not): an
    evaluation (and the checkpoint it evaluated) or a dataset, and the command that takes it."""
    if (path / "meta" / "info.json").is_file():
        return (f"it is a LeRobotDataset, which `so101-sim train --dataset {quote(str(path))} "
                "--out RUN` trains a policy on; ")
    if not (path / "eval_config.json").is_file():
        return ""
    of = ""
    try:  # eval_info.json names the checkpoint as it was typed for that run
        info = json.loads((path / "eval_info.json").read_text(encoding="utf-8"))
        checkpoint = info["config"]["policy_details"]["checkpoint"]
        of = f" of the policy {checkpoint}" if isinstance(checkpoint, str) else ""
    except (OSError, ValueError, KeyError, TypeError):
        pass  # unfinished, or not ours to read: what it is still helps
    return (f"it is an evaluation{of} (the --out of `so101-sim eval`, which `so101-sim compare` "
            "reads); ")


def load_config(path: Path) -> Any:
    import draccus

    try:
        raw = json.loads((path / "config.json").read_text())
        policy_type = raw["type"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path / 'config.json'} is not a lerobot policy config ({exc!r}); "
                         "re-export the checkpoint with policy.save_pretrained()") from exc
    # lerobot's PreTrainedConfig.from_pretrained copies the config to a NamedTemporaryFile
    # (delete=False) that it never removes: one /tmp/tmp*.json per load. draccus.decode of the
    # same fields builds the same config (same errors too) and leaves nothing behind.
    fields = {key: value for key, value in raw.items() if key != "type"}
    try:
        cls = config_class(policy_type)
        with draccus.config_type("json"):
            return draccus.decode(cls, fields)
    except Exception as exc:
        raise ValueError(f"{path / 'config.json'} (policy type {policy_type!r}) could not be "
                         f"parsed by lerobot: {exc}") from exc


def load_weights(cfg: Any, path: Path) -> Any:
    from lerobot.policies.factory import get_policy_class

    try:
        policy_cls = get_policy_class(cfg.type)
    except Exception as exc:
        raise ValueError(f"{path}: lerobot has no policy type {cfg.type!r} ({exc})") from exc
    said = io.StringIO()  # lerobot prints "Loading weights from local directory" on each load
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(said):
            warnings.simplefilter("ignore")
            policy = policy_cls.from_pretrained(path, config=cfg, strict=True)
    except Exception as exc:
        raise RuntimeError(f"{path / 'model.safetensors'} could not be loaded into a "
                           f"{cfg.type!r} policy built from config.json: "
                           f"{type(exc).__name__}: {str(exc)[:300]}") from exc
    finally:  # anything else it printed still shows
        rest = [ln for ln in said.getvalue().splitlines()
                if ln and ln != "Loading weights from local directory"]
        if rest:
            print("\n".join(rest))
    policy.eval()
    policy.reset()
    return policy


def load_processors(cfg: Any, path: Path, device: str) -> tuple[Any, Any]:
    from lerobot.policies.factory import make_pre_post_processors

    try:
        return make_pre_post_processors(
            cfg, pretrained_path=str(path),
            preprocessor_overrides={"device_processor": {"device": device}},
            postprocessor_overrides={"device_processor": {"device": "cpu"}})
    except Exception as exc:
        raise RuntimeError(f"the saved pre/post-processors in {path} could not be loaded: "
                           f"{type(exc).__name__}: {str(exc)[:300]}") from exc


def image_input_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """{camera: (C, H, W)} of the checkpoint's image inputs, from its config.json alone (no
    lerobot); OSError, ValueError, KeyError or TypeError for a file that is not one."""
    features = json.loads((Path(path) / "config.json").read_text())["input_features"]
    return {k[len(IMAGE_PREFIX):]: tuple(int(d) for d in f["shape"])
            for k, f in features.items() if k.startswith(IMAGE_PREFIX)}


def train_image_size(path: Path) -> tuple[int, int] | None:
    f = path / TRAIN_INFO
    if not f.exists():
        return None
    try:
        h, w = (int(v) for v in json.loads(f.read_text())["dataset_image_size"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{f} is invalid ({exc!r}); expected "
                         '{"dataset_image_size": [height, width]}') from exc
    return h, w


def demos_info(task: str | None, task_texts: Any, seeds: list[int] | None) -> dict[str, Any]:
    """The keys above for a dataset: the task it records (``dataset.recorded_task``), lerobot's
    task index (``meta.tasks.index``) and its episodes' seeds (``dataset.recorded_seeds``).
    Without a recorded task (a dataset lerobot's tools rewrote), one text that names one task
    of the suite is that task."""
    ranges: list[list[int]] = []
    for s in sorted(s for s in seeds or () if s >= EVAL_SEED_START):
        if ranges and s <= ranges[-1][1] + 1:
            ranges[-1][1] = s
        else:
            ranges.append([s, s])
    texts = sorted(str(t) for t in task_texts)
    if task is None and len(texts) == 1:
        named = [n for n in available_tasks() if load_task(n).description == texts[0]]
        task = named[0] if len(named) == 1 else None  # pick_place's variants share a text
    return {TASK_KEY: task, TEXTS_KEY: texts, SEEDS_KEY: ranges}


def demos_of(path: str | Path) -> dict[str, Any]:
    """The keys above from a checkpoint's sidecar; for a lerobot-train checkpoint (none), from
    the dataset its ``train_config.json`` names where that folder is here, else the task of its
    so101-sim env ({} for a checkpoint that says neither)."""
    info = read_train_info(path)
    if info is None:
        return _lerobot_train_demos(Path(path))
    return {k: info[k] for k in (TASK_KEY, TEXTS_KEY, SEEDS_KEY) if k in info}


def _lerobot_train_demos(path: Path) -> dict[str, Any]:
    import pandas as pd

    try:  # lerobot-train's config, read as data
        config = json.loads((path / LEROBOT_TRAIN_CONFIG).read_text(encoding="utf-8"))
        root, env = config["dataset"].get("root"), config.get("env") or {}
        data = Path(root).expanduser() if isinstance(root, str) else None  # cwd-relative
        if data is not None and (data / "meta" / "info.json").is_file():
            texts = pd.read_parquet(data / "meta" / "tasks.parquet").index
            return demos_info(recorded_task(data), texts, recorded_seeds(data))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}
    task = env.get("task") if env.get("type") == "so101_pick_place" else None
    return {TASK_KEY: task} if isinstance(task, str) else {}


def ranges_text(ranges: list[list[int]], limit: int = 4) -> str:
    """[[1, 3], [5, 5]] -> "1..3, 5"; past `limit` ranges, ", ..."."""
    shown = ", ".join(f"{lo}..{hi}" if hi > lo else f"{lo}" for lo, hi in ranges[:limit])
    return shown + (", ..." if len(ranges) > limit else "")


def eval_seeds_note(dataset_dir: Path, info: dict[str, Any]) -> str | None:
    """One line when the demos include evaluation seeds, else None."""
    ranges = info.get(SEEDS_KEY) or []
    if not ranges:
        return None
    return (f"so101-sim train: note: {dataset_dir} holds episodes on evaluation seeds "
            f"({ranges_text(ranges)}), e.g. rollouts of `eval --save-rollouts`; eval will "
            "refuse to measure this policy on them (its own training episodes): evaluate it "
            f"with --seed-start above {ranges[-1][1]}")


def checkpoint_name(path: Path) -> str:
    """<run>-<step> for lerobot-train's .../<run>/checkpoints/<step>/pretrained_model, <run>
    for `train`'s final <run>/pretrained_model, else the folder's own name."""
    p = path.resolve()
    if p.name == "pretrained_model" and p.parent.parent.name == "checkpoints":
        return f"{p.parents[2].name}-{p.parent.name}"
    if p.name == "pretrained_model" and p.parent.name:
        return p.parent.name  # every run's final policy would otherwise share one name
    return p.name


def damaged(path: Path, exc: BaseException) -> ValueError:
    """The one-line error for a safetensors file that does not parse (torn or foreign)."""
    return ValueError(f"{path} cannot be read as safetensors ({type(exc).__name__}: {exc}); "
                      "the checkpoint is damaged: save or copy it again")


def read_train_info(path: str | Path) -> dict[str, Any] | None:
    """The checkpoint's ``so101_sim_train.json`` as a dict (None if it has none)."""
    f = Path(path) / TRAIN_INFO
    if not f.is_file():
        return None
    try:
        info = json.loads(f.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{f} is not valid JSON ({exc}); re-export the checkpoint") from exc
    if not isinstance(info, dict):
        raise ValueError(f"{f} holds {type(info).__name__}; expected a JSON object")
    return info


def keep_own_grids(policy: Any, tensors: dict[str, Any]) -> list[str]:
    """Put `policy`'s own spatial-softmax grids into `tensors` where their shapes differ.

    lerobot's ``SpatialSoftmax`` keeps a ``pos_grid`` buffer of the feature map's pixel
    coordinates, fixed by the image size, so a checkpoint of the same architecture at another
    image size differs only there. Returns the keys replaced.
    """
    own = policy.state_dict()
    swapped = [k for k, v in tensors.items()
               if k.endswith(".pos_grid") and k in own and tuple(own[k].shape) != tuple(v.shape)]
    for key in swapped:
        tensors[key] = own[key]
    return swapped


def init_weights_from(policy: Any, path: str | Path) -> dict[str, Any]:
    """Copy the weights of the checkpoint at `path` into `policy` (a new run that fine-tunes it).

    Only ``config.json`` (its policy type) and ``model.safetensors`` are read: tensors, no code.
    The architecture must match exactly, except the spatial-softmax grids, which follow the
    preset's image size (``keep_own_grids``), and a Diffusion checkpoint may have fewer cameras
    or keypoints than the new run (``train.widen``: the new ones start with zero weight in the
    U-Net's conditioning); the new run keeps its own dataset's normalisation.
    Returns what the run records about where it started.
    """
    import hashlib

    from safetensors.torch import load

    path = Path(path).expanduser()
    check_files(path, "--init-from")
    then = load_config(path)
    if then.type != policy.config.type:
        raise ValueError(f"{path} holds a {then.type!r} policy; the preset builds a "
                         f"{policy.config.type!r} one: start from a checkpoint of the same type")
    raw = (path / "model.safetensors").read_bytes()  # read once: loaded and fingerprinted
    try:
        tensors = load(raw)
    except Exception as exc:  # safetensors' own error type: a torn or foreign file
        raise damaged(path / "model.safetensors", exc) from None
    regridded = keep_own_grids(policy, tensors)
    more_kp = widen_keypoints(then, policy.config, tensors, policy.state_dict())
    added = widen_conditioning(then, policy.config, tensors)
    if more_kp:
        print(f"so101-sim train: {path} has {then.spatial_softmax_num_keypoints} keypoints per "
              f"camera, the preset {policy.config.spatial_softmax_num_keypoints}; the new ones "
              "enter the U-Net's conditioning through zero weights, so the run starts from "
              "exactly the checkpoint's actions and learns to use them")
    if added:
        names = ", ".join(k.rsplit(".", 1)[-1] for k in added)
        one = len(added) == 1
        print(f"so101-sim train: {path} was trained without the {names} "
              f"{'camera; it enters' if one else 'cameras; they enter'} the U-Net's "
              "conditioning through zero weights, so the run starts from exactly the "
              f"checkpoint's actions and learns to use {'it' if one else 'them'}")
    if regridded:
        print(f"so101-sim train: {path} was trained on another image size; its "
              f"{counted(len(regridded), 'spatial-softmax coordinate grid')} "
              f"{'is' if len(regridded) == 1 else 'are'} rebuilt for this "
              "preset's (a fixed grid, not learned); every learned weight carries over")
    try:
        policy.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:  # missing/unexpected keys or shapes: another architecture
        lines = str(exc).splitlines()  # torch: a header line, then one line per mismatch
        first = (lines[1:] or lines)[0].strip()[:200]
        raise ValueError(f"{path / 'model.safetensors'} does not fit the preset's "
                         f"{policy.config.type!r} architecture ({first}); start from a "
                         "checkpoint trained with the same preset") from None
    digest = hashlib.sha256(raw).hexdigest()[:16]
    info = read_train_info(path) or {}
    return {"path": str(path.resolve()), "model_sha256": digest, "step": info.get("step"),
            "preset": info.get("preset"), "dataset": info.get("dataset"),
            **({"added_cameras": added} if added else {}),
            **({"added_keypoints": more_kp} if more_kp else {})}


def load_checkpoint(path: str | Path, device: str = "cpu",
                    expect_type: str | None = None) -> tuple[Any, Any, Any, Any]:
    """(config, policy in eval mode, preprocessor, postprocessor) of a checkpoint folder."""
    path = Path(path).expanduser()
    if path.is_dir():  # a crafted processor file is refused first, whatever else is missing
        check_processor_files(path, expect_type)
    check_files(path)
    cfg = load_config(path)
    if expect_type is not None and cfg.type != expect_type:
        raise ValueError(f"{path} holds a {cfg.type!r} policy; expected a {expect_type!r} "
                         "checkpoint")
    check_processor_files(path, cfg.type)  # before lerobot instantiates any step
    cfg.device = device
    policy = load_weights(cfg, path)
    pre, post = load_processors(cfg, path, device)
    return cfg, policy, pre, post

"""What a lerobot checkpoint must look like for the env to feed it, and its fingerprints."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from so101_sim.sim import ENV_STATE_SIZE
from so101_sim.tasks import ALL_CAMERAS as CAMERAS
from so101_sim.train.checkpoint import IMAGE_PREFIX, TRAIN_INFO, damaged

STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
#: Weights of ACT's VAE encoder: it only encodes the demo's action chunk into the latent during
#: training; at inference lerobot's ACT feeds a zero latent, so these never touch an action.
ACT_TRAINING_ONLY = "model.vae_encoder"


#: ``load_policy``'s lerobot options (and the config fields they set) -> ``so101-sim eval``'s
#: flags, for messages
OPTION_FLAGS = {"n_action_steps": "--n-action-steps", "num_inference_steps": "--inference-steps",
                "noise_scheduler": "--noise-scheduler",
                "noise_scheduler_type": "--noise-scheduler",
                "temporal_ensemble_coeff": "--temporal-ensemble", "batch_size": "--policy-batch",
                "precision": "--precision", "camera_map": "--camera-map", "device": "--device"}


def flag_names(options: Any) -> str:
    """``--policy-batch (batch_size), --precision (precision)`` for option names."""
    return ", ".join(f"{OPTION_FLAGS.get(k, k)} ({k})" for k in sorted(options))


def check_features(cfg: Any, path: Path) -> tuple[tuple[str, ...], Any, bool]:
    """The camera names, image size and env-state use the checkpoint expects; errors if the
    env cannot provide them (camera names are matched to env cameras by the caller)."""
    where = f"checkpoint {path}"
    cams: list[str] = []
    sizes: set[tuple[int, int]] = set()
    env_state = False
    expected = (f"expected {STATE_KEY} (6,), {IMAGE_PREFIX}<camera> (3, H, W) for cameras "
                f"{list(CAMERAS)}, and optionally {ENV_STATE_KEY} ({ENV_STATE_SIZE},)")
    for key, ft in cfg.input_features.items():
        shape = tuple(ft.shape)
        if key == STATE_KEY:
            if shape != (6,):
                raise ValueError(f"{where} expects {key} of shape {shape}; the env's agent_pos "
                                 "is (6,) (5 joints in degrees + gripper 0..100)")
        elif key == ENV_STATE_KEY:
            if shape != (ENV_STATE_SIZE,):
                raise ValueError(f"{where} expects {key} of shape {shape}; the env's "
                                 f"environment_state is ({ENV_STATE_SIZE},)")
            env_state = True
        elif key.startswith(IMAGE_PREFIX):
            cam = key[len(IMAGE_PREFIX):]  # env cameras are matched by resolve_camera_map
            if len(shape) != 3 or shape[0] != 3:
                raise ValueError(f"{where} expects {key} of shape {shape}; {expected}")
            cams.append(cam)
            sizes.add((int(shape[1]), int(shape[2])))
        else:
            raise ValueError(f"{where} expects input {key!r}, which the env does not provide; "
                             f"{expected}")
    if len(sizes) > 1:
        raise ValueError(f"{where} expects cameras at different sizes {sorted(sizes)}; the "
                         "harness renders every camera at one size")
    action = cfg.output_features.get("action")
    if action is None or tuple(action.shape) != (6,):
        raise ValueError(f"{where} outputs action of shape "
                         f"{None if action is None else tuple(action.shape)}; the env takes "
                         "(6,) absolute joint targets in LeRobot units")
    return tuple(cams), (sizes.pop() if sizes else None), env_state


def fingerprint(path: Path, settings: dict[str, Any]) -> str:
    """sha256 over the weights, config and processors, plus the inference settings (batch
    size included: results are bitwise reproducible for a fixed one)."""
    h = hashlib.sha256()
    for f in sorted(path.iterdir()):
        if f.is_file() and (f.name in ("config.json", "model.safetensors", TRAIN_INFO)
                            or f.name.startswith(("policy_preprocessor", "policy_postprocessor"))):
            h.update(f.name.encode())
            with f.open("rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:16]


def weights_digest(model_file: Path) -> str:
    """sha256 of the weights alone, each floating tensor as fp16, leaving out ACT's VAE
    encoder: the same for a checkpoint and its `so101-sim export` copy (fp16, no VAE
    encoder), so an export can tell whether an eval measured these weights."""
    from safetensors.torch import load_file

    h = hashlib.sha256()
    try:
        state = load_file(model_file)
    except Exception as exc:  # safetensors' own error type: a torn or foreign file
        raise damaged(model_file, exc) from None
    for name in sorted(k for k in state if not k.startswith(ACT_TRAINING_ONLY)):
        t = state[name].half() if state[name].is_floating_point() else state[name]
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]

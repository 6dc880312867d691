"""Policy presets (`policy/presets/*.toml`): a lerobot policy config plus training settings.

The section that holds the config names the policy: ``[diffusion]`` (`DiffusionConfig`, the
suite's baselines) or ``[act]`` (`ACTConfig`). A preset must set every field of that config that
changes the model or its training, so no lerobot default leaks in silently (0.6.1's defaults
differ from the seed); the loader refuses a preset with a missing or unknown field, and any
section or key it would not read. Only the features (taken from the dataset) and the hub
bookkeeping fields are left out. A variant names ``base = "cpu"`` and sets only what differs.
An optional ``[augment]`` section turns on lerobot's image transforms for training
(`so101_sim.train.augment`).
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from so101_sim.utils.paths import policy_dir
from so101_sim.utils.text import did_you_mean

if TYPE_CHECKING:  # annotations only: presets load without lerobot
    from lerobot.configs.policies import PreTrainedConfig

# Fields that describe where a config came from or goes to, not the model.
NOT_IN_PRESET = frozenset({"input_features", "output_features", "repo_id", "private", "tags",
                           "license", "pretrained_path", "pretrained_revision"})
# TOML has no null: these fields use an empty value to mean None.
_EMPTY_MEANS_NONE = {"pretrained_backbone_weights": "", "resize_shape": [], "crop_shape": [],
                     "temporal_ensemble_coeff": ""}
_TUPLE_FIELDS = {"down_dims", "crop_shape", "resize_shape", "optimizer_betas"}
IMAGE_NORMALIZATIONS = ("imagenet", "dataset")
#: Policy types a preset can train: the TOML section that holds the lerobot config's fields.
POLICY_TYPES = ("diffusion", "act")
# What a preset may hold besides its policy section; anything else is a typo that would
# otherwise be ignored (an `[augmnet]` section would train without augmentation).
_PRESET_KEYS = frozenset({"name", "description", "base", "images", "train", "augment"})
_IMAGE_KEYS = frozenset({"size", "normalize"})


class PresetError(ValueError):
    """A preset file is missing, malformed, or does not set every field."""


@dataclass(frozen=True)
class TrainSettings:
    batch_size: int
    steps: int
    seed: int
    checkpoint_every: int
    log_every: int
    ema_power: float
    ema_max_decay: float
    ema_inv_gamma: float
    ema_min_decay: float
    ema_update_after_step: int
    grad_clip_norm: float = 0.0      # 0: no clipping (the diffusion presets' recipe)
    # Batches come from the decoded frame cache by array indexing in the training process, so
    # there are no loader workers; kept so older presets (num_workers = 0) still load.
    num_workers: int = 0


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    image_size: tuple[int, int]      # frames are resized to this before the policy
    image_normalize: str             # "imagenet" or "dataset" mean/std for pixels
    train: TrainSettings
    policy_type: str                 # "diffusion" or "act": lerobot's config type
    policy: dict[str, Any]           # that config's kwargs, None/tuples restored
    path: Path
    augment: dict[str, Any] | None = None  # [augment]: lerobot ImageTransforms (train/augment.py)


def available_presets() -> list[str]:
    return sorted(p.stem for p in (policy_dir() / "presets").glob("*.toml"))


def preset_path(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml":
        if not p.is_file():
            raise PresetError(f"preset file {str(p)!r} does not exist; pass a preset name "
                              f"({', '.join(available_presets())}) or an existing .toml path")
        return p
    p = policy_dir() / "presets" / f"{name_or_path}.toml"
    if not p.is_file():
        names = available_presets()
        raise PresetError(f"unknown preset {str(name_or_path)!r}"
                          f"{did_you_mean(str(name_or_path), names)}; expected one of {names} "
                          "or a path to a .toml preset")
    return p


def config_class(policy_type: str) -> type:
    """lerobot's config class for a policy type (`DiffusionConfig`, `ACTConfig`)."""
    import lerobot.policies  # noqa: F401  (registers the policy config types)
    from lerobot.configs.policies import PreTrainedConfig

    return PreTrainedConfig.get_choice_class(policy_type)


def _convert_policy(raw: dict[str, Any], policy_type: str, where: Path) -> dict[str, Any]:
    cls = config_class(policy_type)
    expected = {f.name for f in dataclasses.fields(cls)} - NOT_IN_PRESET
    missing, unknown = expected - raw.keys(), raw.keys() - expected
    if missing or unknown:
        raise PresetError(f"{where}: [{policy_type}] must set every {cls.__name__} field exactly "
                          f"once; missing {sorted(missing)}, unknown {sorted(unknown)}. Add the "
                          "missing ones explicitly (lerobot's defaults differ from the seed).")
    out: dict[str, Any] = {}
    for key, value in raw.items():
        if key in _EMPTY_MEANS_NONE and value == _EMPTY_MEANS_NONE[key]:
            value = None
        elif key in _TUPLE_FIELDS:
            value = tuple(value)
        out[key] = value
    from lerobot.configs import NormalizationMode

    out["normalization_mapping"] = {k: NormalizationMode(v)
                                    for k, v in raw["normalization_mapping"].items()}
    return out


def _read_raw(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The preset's TOML, on top of its ``base`` preset's if it names one: a variant (another
    frame size, a wider U-Net) states only what differs, section by section."""
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise PresetError(f"{path}: not valid TOML ({e}); fix the syntax") from None
    base = raw.pop("base", None)
    if base is None:
        return raw
    base_path = preset_path(path.parent / base if str(base).endswith(".toml") else base)
    if base_path.resolve() in seen:
        raise PresetError(f"{path}: base {base!r} leads back to itself; a chain of bases must "
                          "end at a preset without `base`")
    merged = _read_raw(base_path, (*seen, path.resolve()))
    for key, value in raw.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


def _refuse_unknown(path: Path, where: str, table: dict[str, Any], known: frozenset[str] | set[str]
                    ) -> None:
    unknown = sorted(table.keys() - known)
    if unknown:
        key = unknown[0]
        raise PresetError(f"{path}: {where}unknown key {key!r}{did_you_mean(key, known)}; "
                          f"expected among {sorted(known)} (see policy/presets/cpu.toml)")


def load_preset(name_or_path: str | Path) -> Preset:
    """Read and validate a preset by name (`seed`, `cpu`) or .toml path."""
    path = preset_path(name_or_path)
    raw = _read_raw(path, (path.resolve(),))
    _refuse_unknown(path, "", raw, _PRESET_KEYS | set(POLICY_TYPES))
    if isinstance(raw.get("images"), dict):
        _refuse_unknown(path, "[images] ", raw["images"], _IMAGE_KEYS)
    try:
        images, train = raw["images"], raw["train"]
        size = tuple(int(v) for v in images["size"])
        norm = images["normalize"]
        settings = TrainSettings(**train)
        name, description = raw["name"], raw.get("description", "")
    except KeyError as e:
        raise PresetError(f"{path}: missing key {e}; a preset needs name, [images] size/normalize, "
                          "[train] and [diffusion] or [act] (see policy/presets/seed.toml)"
                          ) from None
    except TypeError as e:
        raise PresetError(f"{path}: bad [train] section ({e}); compare with "
                          "policy/presets/seed.toml") from None
    sections = [t for t in POLICY_TYPES if t in raw]
    if len(sections) != 1:
        raise PresetError(f"{path}: has policy sections {sections}; expected exactly one of "
                          f"{['[' + t + ']' for t in POLICY_TYPES]}, which names the policy to "
                          "train (see policy/presets/cpu.toml and act.toml)")
    if settings.num_workers != 0:
        raise PresetError(f"{path}: [train] num_workers = {settings.num_workers!r}, but the "
                          "trainer starts no loader workers: it gathers batches from its "
                          "decoded frame cache in the training process. Remove the key (or set "
                          "it to 0)")
    policy_type = sections[0]
    policy = _convert_policy(raw[policy_type], policy_type, path)
    augment = raw.get("augment")
    if augment is not None:
        from so101_sim.train.augment import transforms_config

        try:
            transforms_config(augment, f"{path}: [augment]")
        except ValueError as e:
            raise PresetError(f"{e} (see policy/presets/cpu_aug.toml)") from None
    if len(size) != 2 or min(size) < 16:
        raise PresetError(f"{path}: [images] size {list(size)} must be [height, width], each >= 16")
    if norm not in IMAGE_NORMALIZATIONS:
        raise PresetError(f"{path}: [images] normalize {norm!r} must be one of "
                          f"{IMAGE_NORMALIZATIONS}")
    return Preset(name=name, description=description, image_size=size, image_normalize=norm,
                  train=settings, policy_type=policy_type, policy=policy, path=path,
                  augment=augment)


def make_config(preset: Preset, input_features: dict, output_features: dict
                ) -> PreTrainedConfig:
    """Build the preset's lerobot config (`DiffusionConfig`, `ACTConfig`) for these features."""
    return config_class(preset.policy_type)(input_features=input_features,
                                            output_features=output_features, **preset.policy)


def policy_features(image_size: tuple[int, int], cameras: tuple[str, ...] = ("front", "side"),
                    state_dim: int = 6) -> tuple[dict, dict]:
    """lerobot input/output features for this env's observations at the policy image size."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    for cam in cameras:
        inputs[f"observation.images.{cam}"] = PolicyFeature(FeatureType.VISUAL,
                                                            (3, *image_size))
    outputs = {"action": PolicyFeature(FeatureType.ACTION, (state_dim,))}
    return inputs, outputs

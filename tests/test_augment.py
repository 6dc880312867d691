"""A preset's [augment] section: lerobot's ImageTransforms on the training frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from so101_sim.record import record
from so101_sim.train.augment import FrameAugmenter
from so101_sim.train.presets import PresetError, load_preset
from so101_sim.train.trainer import TrainError, train

PRESETS = Path(__file__).parents[1] / "policy" / "presets"
BRIGHTNESS = {"max_num_transforms": 1,
              "tfs": {"b": {"type": "ColorJitter", "kwargs": {"brightness": [0.5, 1.5]}}}}


def _tiny_text() -> str:
    """The cpu preset shrunk so a step takes milliseconds (as in test_training.py)."""
    text = (PRESETS / "cpu.toml").read_text()
    for old, new in [('name = "cpu"', 'name = "tiny"'), ("size = [60, 80]", "size = [24, 32]"),
                     ("batch_size = 32", "batch_size = 4"), ("steps = 10000", "steps = 4"),
                     ("checkpoint_every = 500", "checkpoint_every = 2"),
                     ("crop_shape = [54, 72]", "crop_shape = [22, 30]"),
                     ("down_dims = [48, 96, 192]", "down_dims = [16, 32, 64]"),
                     ("diffusion_step_embed_dim = 64", "diffusion_step_embed_dim = 16"),
                     ("spatial_softmax_num_keypoints = 32", "spatial_softmax_num_keypoints = 8")]:
        assert old in text, old
        text = text.replace(old, new)
    return text


AUGMENT_TOML = """
[augment]
max_num_transforms = 2
[augment.tfs.brightness]
type = "ColorJitter"
kwargs = { brightness = [0.5, 1.5] }
[augment.tfs.affine]
type = "RandomAffine"
kwargs = { degrees = [-5.0, 5.0], translate = [0.05, 0.05] }
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("aug") / "ds"
    record(root, 2, image_size=(48, 64), progress=False)
    return root


def test_the_aug_preset_loads_and_bad_sections_are_refused(tmp_path: Path) -> None:
    preset = load_preset("cpu_aug")
    assert preset.augment == {"max_num_transforms": 3, "random_order": False}
    assert preset.policy == load_preset("cpu").policy  # only the frames differ
    assert load_preset("cpu").augment is None
    bad = tmp_path / "bad.toml"
    bad.write_text(_tiny_text() + '\n[augment.tfs.x]\ntype = "NoSuchTransform"\n')
    with pytest.raises(PresetError, match="NoSuchTransform"):
        load_preset(bad)
    bad.write_text(_tiny_text() + "\n[augment]\nmax_transforms = 2\n")
    with pytest.raises(PresetError, match=r"unknown keys \['max_transforms'\] "
                       r"\(did you mean 'max_num_transforms'\?\); expected"):
        load_preset(bad)


def test_each_sample_gets_one_draw_for_all_its_frames() -> None:
    aug = FrameAugmenter(BRIGHTNESS)
    frames = torch.full((16, 2, 3, 12, 16), 0.5)  # 16 samples, To=2 identical frames each
    state = torch.zeros(16, 2, 6)
    torch.manual_seed(0)
    out = aug({"observation.images.front": frames.clone(), "observation.state": state})
    img = out["observation.images.front"]
    assert torch.equal(img[:, 0], img[:, 1])  # one draw covers a sample's frames
    levels = img[:, 0, 0, 0, 0]
    assert len(set(levels.tolist())) == 16  # every sample its own brightness
    assert float(levels.min()) < 0.5 < float(levels.max())
    assert float(img.min()) >= 0.0 and float(img.max()) <= 1.0
    assert out["observation.state"] is state  # only camera keys are touched
    torch.manual_seed(0)
    again = aug({"observation.images.front": frames.clone()})["observation.images.front"]
    assert torch.equal(img, again)  # draws come from torch's RNG, which checkpoints save
    act = aug({"observation.images.side": torch.full((4, 3, 12, 16), 0.5)})  # ACT: no time axis
    assert act["observation.images.side"].shape == (4, 3, 12, 16)


def test_augmented_training_resumes_exactly_and_is_recorded(dataset: Path,
                                                            tmp_path: Path) -> None:
    plain, aug = tmp_path / "plain.toml", tmp_path / "aug.toml"
    plain.write_text(_tiny_text())
    aug.write_text(_tiny_text() + AUGMENT_TOML)
    fixed = {"progress": False, "threads": 1}
    base = train(dataset, tmp_path / "p", preset_name=str(plain), steps=4, **fixed)
    straight = train(dataset, tmp_path / "a", preset_name=str(aug), steps=4, **fixed)
    train(dataset, tmp_path / "b", preset_name=str(aug), steps=4, stop_at=2, **fixed)
    resumed = train(dataset, tmp_path / "b", preset_name=str(aug), steps=4, resume=True, **fixed)
    assert straight.final_loss == resumed.final_loss
    assert straight.final_loss != base.final_loss  # the frames were augmented
    info = json.loads((straight.pretrained_dir / "so101_sim_train.json").read_text())
    assert info["augment"]["tfs"]["affine"]["type"] == "RandomAffine"
    assert info["augment"]["max_num_transforms"] == 2
    plain_info = json.loads((base.pretrained_dir / "so101_sim_train.json").read_text())
    assert plain_info["augment"] is None
    # resuming an augmented run without its [augment] section is a recipe change: refused
    train(dataset, tmp_path / "c", preset_name=str(aug), steps=4, stop_at=2, **fixed)
    aug.write_text(_tiny_text())
    with pytest.raises(TrainError, match=r"differs now \(augment: "):
        train(dataset, tmp_path / "c", preset_name=str(aug), steps=4, resume=True, **fixed)

"""Reading a checkpoint's config.json (train.checkpoint.load_config)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest

from so101_sim.train.checkpoint import load_config

SHIPPED = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"


def test_loading_a_config_leaves_no_temporary_file(tmp_path: Path, monkeypatch) -> None:
    """lerobot's from_pretrained leaves one tmp*.json per call; ours must leave none, and build
    the same config."""
    from lerobot.configs.policies import PreTrainedConfig

    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    cfg = load_config(SHIPPED)
    assert list(temp.iterdir()) == []
    assert cfg == PreTrainedConfig.from_pretrained(SHIPPED)
    assert (cfg.type, cfg.n_action_steps, cfg.horizon) == ("diffusion", 8, 16)


def test_a_config_with_an_unknown_field_names_it(tmp_path: Path) -> None:
    model = tmp_path / "model"
    model.mkdir()
    config = json.loads((SHIPPED / "config.json").read_text())
    config["horizn"] = 16
    (model / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"config.json \(policy type 'diffusion'\) could not be "
                                         r"parsed by lerobot: .*`horizn` are not valid"):
        load_config(model)


def test_loading_the_weights_prints_nothing_of_lerobots(capsys) -> None:
    """lerobot's from_pretrained prints "Loading weights from local directory" on every load,
    a stray line among eval's own; load_weights keeps it out and lets anything else through."""
    from so101_sim.train.checkpoint import load_weights

    policy = load_weights(load_config(SHIPPED), SHIPPED)
    assert policy.config.type == "diffusion"
    assert "Loading weights" not in capsys.readouterr().out

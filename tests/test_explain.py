"""`so101-sim explain`: the walkthrough's page from real modules, on a tiny recorded dataset."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from so101_sim.record import record

SMALL = (48, 64)
SHIPPED = Path(__file__).parents[1] / "policy" / "pick_place_diffusion"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("explain") / "ds"
    record(root, 2, image_size=SMALL, progress=False)
    return root


@pytest.fixture(scope="module")
def seed_page(dataset: Path, tmp_path_factory: pytest.TempPathFactory):
    from so101_sim.explain import explain

    return explain(dataset, None, episode=1, frame=5, k=25,
                   out=tmp_path_factory.mktemp("page"))


def test_page_and_json_are_written(seed_page) -> None:
    page = seed_page.html_path.read_text()
    assert page.startswith("<!DOCTYPE html>") and page.count("data:image/png;base64,") >= 8
    assert "src=\"http" not in page and "href=\"http" not in page  # self-contained
    for step in range(1, 9):
        assert f'<span class="num">{step}</span>' in page
    assert json.loads(seed_page.json_path.read_text()) == json.loads(
        json.dumps(seed_page.numbers))


def test_seed_preset_has_the_walkthrough_shapes(seed_page) -> None:
    n = seed_page.numbers
    enc = n["encoder"]
    assert enc["feature_dim"] == 64 and enc["n_keypoints"] == 32
    assert enc["crop_shape"] == [76, 76] and enc["feature_grid"] == [3, 3]
    assert [s["shape"] for s in enc["stages"] if s["name"] == "layer4"] == [[512, 3, 3]]
    assert enc["global_cond"]["shape"] == [268]
    layout = {seg["name"]: seg["end"] - seg["start"] for seg in enc["global_cond"]["layout"]}
    assert sorted(layout.values()) == [6, 6, 64, 64, 64, 64]
    assert n["timestep"]["embedding_shape"] == [256]
    assert n["timestep"]["full_cond_shape"] == [524]
    assert n["actions"]["shape"] == [16, 6]
    assert n["unet"]["input"] == [16, 6] and n["unet"]["output"] == [16, 6]
    sampling = n["sampling"]
    assert sampling["num_inference_steps"] == 10 and len(sampling["samples"]) == 11
    start, end = sampling["executed"]
    assert end - start == 8
    # the executed rows are the ones predict_action_chunk returned
    np.testing.assert_allclose(np.asarray(sampling["samples"][-1])[start:end],
                               sampling["executed_actions"], rtol=1e-5, atol=1e-4)


def test_loss_on_the_page_is_policy_forward(seed_page, monkeypatch: pytest.MonkeyPatch) -> None:
    """Same batch, same noise and k, through lerobot's own forward: the same loss."""
    n = seed_page.numbers
    eps, k = seed_page.noise, n["noise"]["k"]
    assert torch.equal(eps[0], torch.tensor(n["loss"]["eps"]))
    monkeypatch.setattr(torch, "randn", lambda *a, **kw: eps.clone())
    monkeypatch.setattr(torch, "randint", lambda *a, **kw: torch.tensor([k]))
    with torch.no_grad():
        loss, _ = seed_page.policy.forward(seed_page.batch)
    monkeypatch.undo()
    assert float(loss) == pytest.approx(n["loss"]["mse"], rel=1e-6)
    sq = (np.asarray(n["loss"]["pred"]) - np.asarray(n["loss"]["eps"])) ** 2
    assert sq.mean() == pytest.approx(n["loss"]["mse"], rel=1e-5)
    assert f"{n['loss']['mse']:.6f}" in seed_page.html_path.read_text()
    alpha_bar = seed_page.policy.diffusion.noise_scheduler.alphas_cumprod[k]
    assert n["noise"]["alpha_bar"] == pytest.approx(float(alpha_bar))


def test_keypoints_lie_inside_the_images(seed_page) -> None:
    n, images = seed_page.numbers, seed_page.images
    ch, cw = n["encoder"]["crop_shape"]
    kps = n["encoder"]["keypoints"]
    assert len(kps) == 4  # 2 cameras x To=2
    for name, kp in kps.items():
        cam, step = name.split("/")
        ph, pw = images[f"{cam}/policy/{step}"].shape[:2]
        oh, ow = images[f"{cam}/orig/{step}"].shape[:2]
        assert (oh, ow) == SMALL
        for pts, (h, w) in ((kp["crop_px"], (ch, cw)), (kp["policy_px"], (ph, pw)),
                            (kp["orig_px"], (oh, ow))):
            p = np.asarray(pts)
            assert p.shape == (32, 2)
            assert (p >= -0.5).all() and (p[:, 0] <= w - 0.5).all() and (p[:, 1] <= h - 0.5).all()
        assert np.min(kp["normalised"]) >= -1 and np.max(kp["normalised"]) <= 1


def test_cli_on_the_shipped_checkpoint(dataset: Path, tmp_path: Path) -> None:
    """Shapes are read from the checkpoint (the cpu preset), not the walkthrough's."""
    from so101_sim.cli import main

    assert main(["explain", "--dataset", str(dataset), "--policy", str(SHIPPED),
                 "--frame", "0", "--k", "99", "--out", str(tmp_path)]) == 0
    n = json.loads((tmp_path / "explain.json").read_text())
    assert n["meta"]["policy"]["source"] == "checkpoint"
    assert n["encoder"]["crop_shape"] == [54, 72] and n["encoder"]["feature_grid"] == [2, 3]
    assert n["timestep"]["full_cond_shape"] == [64 + 268]
    assert n["noise"]["k"] == 99
    assert n["state"]["is_pad"] == [True, False]  # frame 0: t-1 is a padding copy
    assert (tmp_path / "explain.html").stat().st_size > 10_000


def test_refuses_bad_input(dataset: Path, tmp_path: Path) -> None:
    from so101_sim.explain import ExplainError, explain
    from so101_sim.utils.trust import UntrustedCheckpointError

    with pytest.raises(ExplainError, match="--episode 5"):
        explain(dataset, episode=5, write=False)
    with pytest.raises(ExplainError, match="--frame 100000"):
        explain(dataset, frame=100_000, write=False)
    bad = tmp_path / "ckpt"
    bad.mkdir()
    for name in ("config.json", "model.safetensors"):
        shutil.copy(SHIPPED / name, bad / name)
    spec = json.loads((SHIPPED / "policy_preprocessor.json").read_text())
    spec["steps"][0] = {"class": "os.system", "config": {}}
    (bad / "policy_preprocessor.json").write_text(json.dumps(spec))
    with pytest.raises(UntrustedCheckpointError):
        explain(dataset, bad, write=False)
    # an ACT preset crashed inside lerobot (no rgb-encoder option); --preset beside --policy
    # was ignored
    with pytest.raises(ExplainError, match="--preset act is an 'act' preset; explain follows "
                                           "Diffusion Policy"):
        explain(dataset, preset="act", write=False)
    with pytest.raises(ExplainError, match="--preset cpu given with --policy"):
        explain(dataset, SHIPPED, preset="cpu", write=False)

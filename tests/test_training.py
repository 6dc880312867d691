"""Presets, the trainer's batches, exact resume, and the checkpoint format lerobot loads."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_presets import shrunk_preset, tiny_act_preset, tiny_preset

from so101_sim.dataset import DEFAULT_REPO_ID
from so101_sim.record import record
from so101_sim.train import trainer
from so101_sim.train.demos import frames_note, gather_batch, load_demos
from so101_sim.train.presets import PresetError, load_preset, make_config, policy_features
from so101_sim.train.state import list_checkpoints
from so101_sim.train.trainer import TrainError, train

SMALL = (48, 64)
FPS = 30


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("train") / "ds"
    record(root, 2, image_size=SMALL, progress=False)
    return root


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_preset(tmp_path_factory.mktemp("preset"))


def test_seed_preset_has_the_walkthrough_shapes() -> None:
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    preset = load_preset("seed")
    cfg = make_config(preset, *policy_features(preset.image_size))
    assert (cfg.n_obs_steps, cfg.horizon, cfg.n_action_steps) == (2, 16, 8)
    assert cfg.noise_scheduler_type == "DDIM" and cfg.num_inference_steps == 10
    assert cfg.pretrained_backbone_weights is None and cfg.use_group_norm
    policy = DiffusionPolicy(cfg).eval()
    model = policy.diffusion
    assert model.rgb_encoder.feature_dim == 64
    assert model.noise_scheduler.config.num_train_timesteps == 100
    assert model.noise_scheduler.config.beta_schedule == "squaredcos_cap_v2"
    b = 2
    batch = {"observation.state": torch.randn(b, 2, 6),
             "observation.images": torch.rand(b, 2, 2, 3, *preset.image_size)}
    with torch.no_grad():
        cond = model._prepare_global_conditioning(batch)
        film = model.unet.down_modules[0][0].cond_encoder[-1]
        actions = model.generate_actions(batch)
    assert cond.shape == (b, 268)
    assert film.in_features == 524  # 268 + step embedding 256
    assert actions.shape == (b, 8, 6)  # Ta=8 of the Tp=16 chunk
    # every group norm has C/16 groups, as the walkthrough replaces BatchNorm
    norms = [m for m in model.rgb_encoder.modules() if isinstance(m, torch.nn.GroupNorm)]
    assert norms and all(m.num_groups == m.num_channels // 16 for m in norms)


def test_cpu_preset_fits_the_shipping_limit() -> None:
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    preset = load_preset("cpu")
    policy = DiffusionPolicy(make_config(preset, *policy_features(preset.image_size)))
    n = sum(p.numel() for p in policy.parameters())
    assert n * 2 <= 30e6, f"{n} parameters do not fit 30 MB in fp16"


def test_preset_must_set_every_field(tmp_path: Path) -> None:
    text = (Path(__file__).parents[1] / "policy" / "presets" / "cpu.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("horizon = 16\n", ""))
    with pytest.raises(PresetError, match="missing \\['horizon'\\]"):
        load_preset(bad)
    bad.write_text(text + "\n[augmnet]\nbrightness = [0.8, 1.2]\n")  # would train without it
    with pytest.raises(PresetError, match="unknown key 'augmnet' \\(did you mean 'augment'\\?\\)"):
        load_preset(bad)
    bad.write_text(text.replace('normalize = "imagenet"', 'normalize = "imagenet"\nsizes = [1]'))
    with pytest.raises(PresetError, match="\\[images\\] unknown key 'sizes'"):
        load_preset(bad)
    bad.write_text(text.replace("horizon = 16\n", "horizon = 16\nhorizonn = 3\n"))
    with pytest.raises(PresetError, match="unknown \\['horizonn'\\]"):
        load_preset(bad)
    with pytest.raises(PresetError, match="unknown preset 'nope'"):
        load_preset("nope")


def test_loader_workers_that_would_not_start_are_refused(tmp_path: Path) -> None:
    """The trainer has no data loader, so a preset asking for loader workers is told so rather
    than trained on one process as if it had them; the old `num_workers = 0` still loads."""
    text = (Path(__file__).parents[1] / "policy" / "presets" / "cpu.toml").read_text()
    old = tmp_path / "old.toml"
    old.write_text(text.replace("log_every = 50\n", "log_every = 50\nnum_workers = 0\n"))
    assert load_preset(old).train.num_workers == 0
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("log_every = 50\n", "log_every = 50\nnum_workers = 4\n"))
    with pytest.raises(PresetError, match=r"bad.toml: \[train\] num_workers = 4, but the trainer "
                                          r"starts no loader workers.*Remove the key"):
        load_preset(bad)


def test_batches_match_lerobot_dataset(dataset: Path, tiny: Path) -> None:
    """gather_batch gives what LeRobotDataset with delta_timestamps gives, padding included."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    preset = load_preset(tiny)
    cfg = make_config(preset, *policy_features(preset.image_size))
    delta = {"observation.state": [i / FPS for i in cfg.observation_delta_indices],
             "action": [i / FPS for i in cfg.action_delta_indices]}
    ds = LeRobotDataset(DEFAULT_REPO_ID, root=dataset, delta_timestamps=delta)
    demos = load_demos(ds, preset, None)
    ends = [int(r["dataset_to_index"]) for r in ds.meta.episodes]
    idx = np.array([0, 5, ends[0] - 9, ends[0] - 1, ends[0], ends[1] - 1])
    ours = gather_batch(demos, idx, cfg.observation_delta_indices,
                        cfg.action_delta_indices)
    for row, i in enumerate(idx):
        item = ds[int(i)]
        assert torch.equal(ours["observation.state"][row], item["observation.state"])
        assert torch.equal(ours["action"][row], item["action"])
        assert torch.equal(ours["action_is_pad"][row], item["action_is_pad"])
    assert ours["action_is_pad"][3].sum() == cfg.horizon - 2  # last frame: only t-1, t real
    assert ours["observation.images.front"].shape == (len(idx), 2, 3, *preset.image_size)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return load_file(path / "model.safetensors")


def test_stop_at_is_the_prefix_of_the_long_run(dataset: Path, tiny: Path,
                                               tmp_path: Path) -> None:
    """--stop-at pauses on the long run's schedule; --resume then finishes it exactly."""
    fixed = {"progress": False, "threads": 1, "log_every": 1}
    straight = train(dataset, tmp_path / "a", preset_name=str(tiny), steps=6, **fixed)
    paused = train(dataset, tmp_path / "b", preset_name=str(tiny), steps=6, stop_at=3, **fixed)
    assert paused.step == 3 and paused.pretrained_dir.parent.name == "step_0000003"
    assert not (tmp_path / "b" / "pretrained_model").exists()
    # a finished run drops its decoded frames; a paused one keeps them for --resume
    assert not (tmp_path / "a" / "frame_cache").exists()
    assert any((tmp_path / "b" / "frame_cache").glob("*.npy"))
    log_a = [json.loads(x) for x in (tmp_path / "a" / "train_log.jsonl").read_text().splitlines()]
    log_b = [json.loads(x) for x in (tmp_path / "b" / "train_log.jsonl").read_text().splitlines()]
    assert [r["lr"] for r in log_b] == [r["lr"] for r in log_a[:3]]
    with pytest.raises(TrainError, match="already at step 3"):
        train(dataset, tmp_path / "b", preset_name=str(tiny), steps=6, stop_at=2, resume=True,
              **fixed)
    with pytest.raises(TrainError, match="is outside 1"):
        train(dataset, tmp_path / "c", preset_name=str(tiny), steps=6, stop_at=7, **fixed)
    resumed = train(dataset, tmp_path / "b", preset_name=str(tiny), steps=6, resume=True, **fixed)
    a, b = _weights(straight.pretrained_dir), _weights(resumed.pretrained_dir)
    assert resumed.step == 6 and all(torch.equal(a[k], b[k]) for k in a)


def test_a_signal_in_the_loop_saves_and_resumes(dataset: Path, tiny: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C mid-run (SIGTERM takes the same handler): the step in progress finishes, a
    checkpoint is saved, the message names both, and --resume finishes the run."""
    from so101_sim.train.state import TrainingStopped

    sig = signal.SIGINT

    calls = []

    def gather_then_signal(*args: object, **kwargs: object) -> object:
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), sig)
        return gather_batch(*args, **kwargs)

    monkeypatch.setattr(trainer, "gather_batch", gather_then_signal)
    before = signal.getsignal(sig)
    with pytest.raises(TrainingStopped, match=rf"stopped by signal {int(sig)} at step 3; "
                                              r"checkpoint .*step_0000003"):
        train(dataset, tmp_path / "r", preset_name=str(tiny), steps=5, progress=False,
              threads=1)
    assert signal.getsignal(sig) is before
    assert list_checkpoints(tmp_path / "r")[-1].name == "step_0000003"
    monkeypatch.undo()
    done = train(dataset, tmp_path / "r", preset_name=str(tiny), steps=5, resume=True,
                 progress=False, threads=1)
    assert done.step == 5 and done.pretrained_dir == tmp_path / "r" / "pretrained_model"


def test_resume_continues_exactly(dataset: Path, tiny: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    # a fixed thread count: the adaptive one may cut steps into parts if the machine is busy
    fixed = {"progress": False, "threads": 1}
    straight = train(dataset, tmp_path / "a", preset_name=str(tiny), steps=4,
                     keep_frame_cache=True, **fixed)
    assert any((tmp_path / "a" / "frame_cache").glob("*.npy"))
    train(dataset, tmp_path / "b", preset_name=str(tiny), steps=2, **fixed)
    # b finished at 2 and dropped its frames: stretching it to 4 decodes again, same result
    assert not (tmp_path / "b" / "frame_cache").exists()
    with pytest.raises(TrainError, match="--resume"):
        train(dataset, tmp_path / "b", preset_name=str(tiny), steps=4, **fixed)
    # as if b's first two steps had run on another torch: the resume says so, records both
    state_path = tmp_path / "b" / "checkpoints" / "step_0000002" / "training_state.pt"
    state = torch.load(state_path, weights_only=True)
    [[first, now]] = state["setup_history"]
    then = {**now, "software": {**now["software"], "torch": "0.0.1"}}
    torch.save({**state, "setup_history": [[first, then]]}, state_path)
    capsys.readouterr()
    resumed = train(dataset, tmp_path / "b", preset_name=str(tiny), steps=4, resume=True,
                    **fixed)
    assert (f"resuming at step 2 on another setup (torch 0.0.1 vs {now['software']['torch']}, "
            "then vs now)") in capsys.readouterr().out
    assert json.loads((resumed.pretrained_dir / "so101_sim_train.json").read_text())[
        "setup_history"] == [[0, then], [2, now]]
    assert straight.step == resumed.step == 4
    a, b = _weights(straight.pretrained_dir), _weights(resumed.pretrained_dir)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert straight.final_loss == resumed.final_loss
    log_a = [json.loads(x) for x in (tmp_path / "a" / "train_log.jsonl").read_text().splitlines()]
    log_b = [json.loads(x) for x in (tmp_path / "b" / "train_log.jsonl").read_text().splitlines()]
    assert [r["loss"] for r in log_a] == [r["loss"] for r in log_b]
    info = json.loads((straight.pretrained_dir / "so101_sim_train.json").read_text())
    assert info["dataset_image_size"] == list(SMALL) and info["policy_image_size"] == [24, 32]
    assert info["setup_history"] == [[0, now]]  # one setup all along
    assert info["weights"] == "EMA" and info["step"] == 4
    # the same command again on the finished run: nothing trained, nothing saved over (it
    # used to save step 4 again with a NaN loss); without --steps a resume keeps the run's
    # own total (it fell back to the preset's), and a different batch size is refused
    last = tmp_path / "b" / "checkpoints" / "step_0000004" / "pretrained_model"
    sidecar = (last / "so101_sim_train.json").read_bytes()
    again = train(dataset, tmp_path / "b", preset_name=str(tiny), resume=True, **fixed)
    assert (again.step, again.final_loss, again.samples_per_s) == (4, resumed.final_loss, 0.0)
    assert (last / "so101_sim_train.json").read_bytes() == sidecar
    with pytest.raises(TrainError, match=r"--steps 3: .* is already at step 4"):
        train(dataset, tmp_path / "b", preset_name=str(tiny), steps=3, resume=True, **fixed)
    with pytest.raises(TrainError, match=f"trained at --batch-size {info['batch_size']}, not "
                                         f"{info['batch_size'] + 1}; resume without"):
        train(dataset, tmp_path / "b", preset_name=str(tiny), steps=6,
              batch_size=info["batch_size"] + 1, resume=True, **fixed)


def test_resume_refuses_a_dataset_that_changed(dataset: Path, tiny: Path,
                                                tmp_path: Path) -> None:
    """Episodes recorded into the dataset after the run started: resuming would draw from
    other frames than the run's first steps did."""
    import shutil

    grown = tmp_path / "ds"
    shutil.copytree(dataset, grown)
    fixed = {"progress": False, "threads": 1}
    train(grown, tmp_path / "run", preset_name=str(tiny), steps=4, stop_at=1, **fixed)
    record(grown, 3, resume=True, progress=False)
    with pytest.raises(TrainError, match=r"trained on 2 episodes \(\d+ frames\) of .*, which "
                                         r"now holds 3 .* fine-tune on it in a new run with "
                                         "--init-from"):
        train(grown, tmp_path / "run", preset_name=str(tiny), steps=4, resume=True, **fixed)


def test_busy_machine_steps_in_parts(dataset: Path, tiny: Path, tmp_path: Path,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """With a neighbour sensed, steps run in 2 batch parts: same loss scale, logged, trains."""

    class Busy(trainer.AdaptiveThreads):
        def __init__(self) -> None:
            super().__init__(cores=2, sense=False)
            self.parts = 2
            self._set(1)

        def after_step(self, step: int, seconds: float) -> None:
            pass

    whole = train(dataset, tmp_path / "w", preset_name=str(tiny), steps=3, progress=False,
                  threads=1)
    monkeypatch.setattr(trainer, "AdaptiveThreads", Busy)
    parts = train(dataset, tmp_path / "p", preset_name=str(tiny), steps=3, progress=False)
    rows = [json.loads(x) for x in (tmp_path / "p" / "train_log.jsonl").read_text().splitlines()]
    assert {r["parts"] for r in rows} == {2} and {r["threads"] for r in rows} == {1}
    # the same batches with other noise draws: the summed part losses are the batch mean
    assert np.isfinite(parts.final_loss)
    assert 0.7 < parts.final_loss / whole.final_loss < 1.4
    a, b = _weights(whole.pretrained_dir), _weights(parts.pretrained_dir)
    assert any(not torch.equal(a[k], b[k]) for k in a)  # it trained, with its own draws


def test_more_threads_than_cores_get_one_line(dataset: Path, tiny: Path, tmp_path: Path,
                                              monkeypatch, capsys) -> None:
    """`train --threads 8` on 2 cores took 34x as long a step as `--threads 2`, unsaid. Kept
    as asked (a fixed count is what repeats bitwise elsewhere), with one line."""
    from so101_sim.utils import devices

    monkeypatch.setattr(devices, "cpu_count", lambda: 1)  # 2 threads: over, yet cheap here
    train(dataset, tmp_path / "r", preset_name=str(tiny), steps=1, progress=False, threads=2)
    out = capsys.readouterr().out
    assert out.count("so101-sim train: note: --threads 2 is more than the 1 CPU core this "
                     "process can use") == 1
    assert "--threads 1 or fewer, or leave it out" in out
    train(dataset, tmp_path / "s", preset_name=str(tiny), steps=1, progress=False, threads=1)
    assert "--threads" not in capsys.readouterr().out


def test_bf16_precision_trains_and_is_recorded(dataset: Path, tiny: Path, tmp_path: Path) -> None:
    """bf16 autocast gives a finite loss and fp32 weights; switching on --resume is recorded."""
    train(dataset, tmp_path / "r", preset_name=str(tiny), steps=2, progress=False)
    r = train(dataset, tmp_path / "r", preset_name=str(tiny), steps=4, resume=True,
              progress=False, precision="bf16")
    assert np.isfinite(r.final_loss)
    assert {v.dtype for v in _weights(r.pretrained_dir).values()} == {torch.float32}
    info = json.loads((r.pretrained_dir / "so101_sim_train.json").read_text())
    assert info["precision"] == "bf16"
    assert info["precision_history"] == [[0, "fp32"], [2, "bf16"]]
    with pytest.raises(TrainError, match="precision='fp16' is invalid"):
        train(dataset, tmp_path / "x", preset_name=str(tiny), steps=1, precision="fp16")


@pytest.mark.usefixtures("lerobot_tempfiles")
def test_checkpoint_loads_through_lerobot(dataset: Path, tiny: Path, tmp_path: Path) -> None:
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    r = train(dataset, tmp_path / "run", preset_name=str(tiny), steps=2, progress=False)
    policy = DiffusionPolicy.from_pretrained(r.pretrained_dir).eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(r.pretrained_dir))
    obs = {"observation.state": torch.zeros(1, 6),
           "observation.images.front": torch.rand(1, 3, 24, 32),
           "observation.images.side": torch.rand(1, 3, 24, 32)}
    with torch.no_grad():
        action = post(policy.select_action(pre(obs)))
    assert action.shape == (1, 6) and torch.isfinite(action).all()
    # what the demos were of, for eval's and curve's default --task (tests/test_trained_on.py)
    info = json.loads((r.pretrained_dir / "so101_sim_train.json").read_text())
    assert info["dataset_task"] == "pick_place"
    assert info["dataset_task_texts"] == ["Pick up the red cube and place it on the green target."]
    # the EMA weights differ from the raw ones after training
    # the training state holds tensors and plain values only: it loads without unpickling code
    raw = torch.load(next((tmp_path / "run" / "checkpoints").glob("*/training_state.pt")),
                     weights_only=True)["model"]
    ema = _weights(r.pretrained_dir)
    assert any(not torch.equal(raw[k], ema[k]) for k in ema if k in raw)
    # the shipped form: fp16 on disk, fp32 after lerobot loads it, and a model card
    from so101_sim.harness.export import export_policy

    shipped = export_policy(r.pretrained_dir, tmp_path / "shipped")
    assert all(v.dtype == torch.float16 for v in _weights(shipped).values()
               if v.is_floating_point())
    loaded = DiffusionPolicy.from_pretrained(shipped)
    assert all(p.dtype == torch.float32 for p in loaded.parameters())
    ref = dict(policy.named_parameters())
    assert max((p - ref[n]).abs().max().item() for n, p in loaded.named_parameters()) < 1e-2
    card = (shipped / "README.md").read_text()
    assert "| steps | 2 of 2 planned, batch 4 |" in card and "not measured yet" in card


@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_lerobot_eval_runs_the_checkpoint(dataset: Path, tiny: Path, tmp_path: Path) -> None:
    r = train(dataset, tmp_path / "run", preset_name=str(tiny), steps=1, progress=False)
    exe = Path(sys.executable).parent / "lerobot-eval"
    out = tmp_path / "eval"
    proc = subprocess.run(
        [str(exe), "--env.type=so101_pick_place",
         "--env.discover_packages_path=so101_sim.lerobot_plugin",
         "--env.image_height=24", "--env.image_width=32", "--env.episode_length=40",
         f"--policy.path={r.pretrained_dir}", "--eval.n_episodes=1", "--eval.batch_size=1",
         "--policy.device=cpu", f"--output_dir={out}"],
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads(next(out.rglob("eval_info.json")).read_text())
    assert info["overall"]["n_episodes"] == 1


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_before_the_training_loop_is_one_line(tmp_path: Path, sig: signal.Signals,
                                                       monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture) -> None:
    """A signal while a run starts (imports, decoding frames: minutes on a big dataset) used
    to end it with "so101-sim train: ; continue with --resume" (Ctrl-C: an empty message and
    nothing to resume) or silently with -15 (SIGTERM). Now both say what the folder holds."""
    from so101_sim.cli import main

    run = tmp_path / "run"

    def starting(dataset: Path, out: Path, **_: object) -> None:
        (out / "frame_cache").mkdir(parents=True, exist_ok=True)
        (out / "frame_cache" / "front.npy").write_bytes(b"")
        os.kill(os.getpid(), sig)  # as if it came while frames were being decoded
        time.sleep(10)
        raise AssertionError(f"{sig.name} did not stop the start-up")

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(trainer, "train", starting)
    assert main(["train", "--dataset", str(tmp_path / "ds"), "--out", str(run)]) == 130
    assert capsys.readouterr().err.strip() == (
        "so101-sim train: interrupted before the first checkpoint; nothing to resume: run the "
        "same command again (the frames decoded so far are kept in its frame_cache)")
    assert signal.getsignal(signal.SIGTERM) is before  # the command's handler is gone again

    (run / "checkpoints" / "step_0000004").mkdir(parents=True)
    (run / "checkpoints" / "step_0000004" / "training_state.pt").write_bytes(b"")
    assert main(["train", "--dataset", str(tmp_path / "ds"), "--out", str(run), "--resume"]) \
        == 130
    assert capsys.readouterr().err.strip() == (
        f"so101-sim train: interrupted; {run} keeps its last checkpoint, step_0000004; continue "
        "with --resume")


def test_bad_dataset_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrainError, match="not a LeRobotDataset"):
        train(tmp_path, tmp_path / "out", preset_name="cpu", steps=1, progress=False)


def test_resume_refuses_a_preset_whose_architecture_changed(dataset: Path, tiny: Path,
                                                            tmp_path: Path) -> None:
    """Same preset name, other U-Net: a one-line refusal naming the change, not a traceback."""
    preset = tmp_path / "tiny.toml"
    preset.write_text(tiny.read_text())
    train(dataset, tmp_path / "run", preset_name=str(preset), steps=2, progress=False)
    preset.write_text(tiny.read_text().replace("down_dims = [16, 32, 64]",
                                               "down_dims = [16, 32, 32]"))
    with pytest.raises(TrainError, match=r"differs now \(down_dims: \[16, 32, 64\] -> "
                                         r"\[16, 32, 32\]\)"):
        train(dataset, tmp_path / "run", preset_name=str(preset), steps=4, resume=True,
              progress=False)


def test_init_from_starts_a_new_run_from_a_checkpoint(dataset: Path, tiny: Path,
                                                     tmp_path: Path) -> None:
    """--init-from: a new run begins at the checkpoint's weights (its first warm-up step has lr
    0, so one step keeps them bit for bit), every sidecar and the card say where it started,
    and a checkpoint that cannot fit is refused in one line."""
    fixed = {"progress": False, "threads": 1, "log_every": 1}
    base = train(dataset, tmp_path / "base", preset_name=str(tiny), steps=2, **fixed)
    tuned = train(dataset, tmp_path / "tuned", preset_name=str(tiny), steps=4, stop_at=1,
                  init_from=base.pretrained_dir, **fixed)
    a, b = _weights(base.pretrained_dir), _weights(tuned.pretrained_dir)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    resumed = train(dataset, tmp_path / "tuned", preset_name=str(tiny), steps=4, resume=True,
                    **fixed)
    c = _weights(resumed.pretrained_dir)
    assert any(not torch.equal(a[k], c[k]) for k in a)  # it then trains
    for ck in (tuned.pretrained_dir, resumed.pretrained_dir):
        started = json.loads((ck / "so101_sim_train.json").read_text())["init_from"]
        assert started["path"] == str(base.pretrained_dir.resolve()) and started["step"] == 2
    from so101_sim.harness.export import export_policy

    card = (export_policy(resumed.pretrained_dir, tmp_path / "shipped") / "README.md").read_text()
    assert "| started from | `base`, step 2 (model.safetensors sha256" in card
    with pytest.raises(TrainError, match=r"--resume continues .* drop one of them"):
        train(dataset, tmp_path / "tuned", preset_name=str(tiny), steps=4, resume=True,
              init_from=base.pretrained_dir, **fixed)
    shipped = Path(__file__).parents[1] / "policy" / "suite_diffusion"
    with pytest.raises(TrainError, match="does not fit the preset's 'diffusion' architecture "
                                         r"\(size mismatch for "):
        train(dataset, tmp_path / "other", preset_name=str(tiny), steps=2, init_from=shipped,
              **fixed)
    with pytest.raises(TrainError, match=r"--init-from: policy checkpoint .* has no config\.json"
                       r"; did you mean --init-from .*base/pretrained_model\? ") as caught:
        train(dataset, tmp_path / "other", preset_name=str(tiny), steps=2,
              init_from=tmp_path / "base", **fixed)
    assert "--policy" not in str(caught.value)  # eval's flag and its expert: not train's
    assert not list_checkpoints(tmp_path / "other")


def test_init_from_another_image_size_rebuilds_only_the_softmax_grid(tmp_path: Path,
                                                                    capsys) -> None:
    """A 48x64 checkpoint fine-tunes at 96x128 (preset cpu96_ft): every learned weight carries
    over, the spatial softmax keeps the coordinate grid of its own feature map, one line says
    so; a learned weight of another shape is still refused."""
    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_policy import make_tiny_diffusion_checkpoint

    from so101_sim.train.checkpoint import init_weights_from, load_config, load_weights

    small = make_tiny_diffusion_checkpoint(tmp_path / "small", input_size=(48, 64))
    large = make_tiny_diffusion_checkpoint(tmp_path / "large", input_size=(96, 128), seed=1)
    policy = load_weights(load_config(large), large)
    grids = {k: v.clone() for k, v in policy.state_dict().items() if k.endswith("pos_grid")}
    init_weights_from(policy, small)
    assert "1 spatial-softmax coordinate grid is rebuilt" in capsys.readouterr().out
    want, got = _weights(small), policy.state_dict()
    assert grids and all(tuple(want[k].shape) != tuple(g.shape) for k, g in grids.items())
    for key, value in got.items():
        assert torch.equal(value, grids[key] if key in grids else want[key]), key
    narrow = make_tiny_diffusion_checkpoint(tmp_path / "narrow", input_size=(96, 128),
                                            cameras=("front",))
    with pytest.raises(ValueError, match="does not fit the preset's 'diffusion' architecture"):
        init_weights_from(load_weights(load_config(narrow), narrow), small)
    assert load_preset("cpu96_ft").image_size == (96, 128)


def test_nocrop_preset_sees_the_whole_frame_and_takes_the_suite_weights(capsys) -> None:
    """cpu_ft_nocrop: no crop in training either (two train-mode encodes of one image agree,
    where cpu_ft's random crops do not), and the shipped 60x80 suite weights load unchanged,
    grids included, since the whole 60x80 frame gives the same 2x3 feature map as the crop."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    from so101_sim.train.checkpoint import init_weights_from
    from so101_sim.utils.paths import policy_dir

    encodes = {}
    for name in ("cpu_ft", "cpu_ft_nocrop"):
        preset = load_preset(name)
        torch.manual_seed(0)
        policy = DiffusionPolicy(make_config(preset, *policy_features(preset.image_size)))
        if name == "cpu_ft_nocrop":
            assert preset.policy["crop_shape"] is None and preset.image_size == (60, 80)
            init_weights_from(policy, policy_dir() / "suite_diffusion")
            assert "grid" not in capsys.readouterr().out  # nothing rebuilt: the same 2x3 map
        encoder = policy.diffusion.rgb_encoder.train()
        image = torch.rand(1, 3, *preset.image_size, generator=torch.Generator().manual_seed(1))
        with torch.no_grad():
            encodes[name] = [encoder(image) for _ in range(4)]
    assert all(torch.equal(e, encodes["cpu_ft_nocrop"][0]) for e in encodes["cpu_ft_nocrop"])
    assert not all(torch.equal(e, encodes["cpu_ft"][0]) for e in encodes["cpu_ft"])


def test_success_curve_goes_into_the_card(dataset: Path, tiny: Path, tmp_path: Path) -> None:
    """`so101-sim curve` evaluates each saved checkpoint on the same seeds; export draws it."""
    from so101_sim.harness.curve import evaluate_curve
    from so101_sim.harness.export import export_policy

    run = tmp_path / "run"
    train(dataset, run, preset_name=str(tiny), steps=4, progress=False)
    rows = evaluate_curve(run, episodes=1, n_envs=1, progress=False)
    assert [r["step"] for r in rows] == [2, 4]
    assert all(r["episodes"] == 1 and r["successes"] in (0, 1) for r in rows)
    again = evaluate_curve(run, episodes=1, n_envs=1, progress=False)  # nothing left to run
    assert again == rows
    # a multi-task run has a curve per task: lift's rows are its own, pick_place's stay
    lift = evaluate_curve(run, episodes=1, n_envs=1, steps=[4], task="lift", progress=False)
    assert [(r["task"], r["step"]) for r in lift] == [("lift", 4)]
    assert evaluate_curve(run, episodes=1, n_envs=1, progress=False) == rows
    shipped = export_policy(run / "checkpoints" / "step_0000004" / "pretrained_model",
                            tmp_path / "shipped")
    card = (shipped / "README.md").read_text()
    assert "![success against training](curve.png)" in card and (shipped / "curve.png").is_file()
    assert "| 4 | " in card
    # a multi-task checkpoint: one eval per task, stored per task, one card row per task
    from so101_sim.harness.export import recorded_eval

    evals = [run / "eval_curve" / t / "step_0000004" for t in ("pick_place", "lift")]
    suite = export_policy(run / "checkpoints" / "step_0000004" / "pretrained_model",
                          tmp_path / "suite", evals)
    card = (suite / "README.md").read_text()
    assert card.startswith("# suite: Diffusion Policy for so101_sim/PickPlace-v0, tasks "
                           "pick_place, lift")
    for task in ("pick_place", "lift"):
        info = json.loads(recorded_eval(suite, task).read_text())
        assert recorded_eval(suite, task).name == f"eval_info_{task}.json"
        assert info["config"]["task"] == task
        assert f"| success on {task} | **{info['aggregated']['pc_success']:.1f}%**" in card
        assert f"| {task} | 4 | " in card  # its curve row
    assert "--task pick_place,lift" in card and not (suite / "eval_info.json").exists()
    with pytest.raises(ValueError, match="measure a task twice"):
        export_policy(run / "checkpoints" / "step_0000004" / "pretrained_model",
                      tmp_path / "twice", evals + evals[:1])
    # one `eval --task a,b` folder stands for its per-task folders
    from so101_sim.harness.suite import evaluate_suite

    ck = run / "checkpoints" / "step_0000004" / "pretrained_model"
    evaluate_suite(str(ck), ["lift", "pick_place"], out_dir=tmp_path / "both", episodes=1,
                   n_envs=1, progress=False, videos=0, log=lambda _: None)
    both = export_policy(ck, tmp_path / "both_export", [tmp_path / "both"])
    assert sorted(p.name for p in both.glob("eval_info_*.json")) == [
        "eval_info_lift.json", "eval_info_pick_place.json"]


def test_export_checks_what_an_eval_measured_and_what_it_replaces(
        dataset: Path, tiny: Path, tmp_path: Path) -> None:
    """An eval records its weights, the same digest for a checkpoint and its fp16 export, so
    an export refuses an eval of other weights (its numbers would go into this card). An
    export replaces its folder whole: a folder of other files is refused, another policy's
    export needs replace=True, the same checkpoint again does not."""
    from so101_sim.harness import evaluate
    from so101_sim.harness.export import export_policy
    from so101_sim.harness.policies.checks import weights_digest

    run = tmp_path / "run"
    train(dataset, run, preset_name=str(tiny), steps=4, progress=False)
    two, four = (run / "checkpoints" / f"step_{s:07d}" / "pretrained_model" for s in (2, 4))
    shipped = export_policy(four, tmp_path / "shipped")
    assert weights_digest(shipped / "model.safetensors") == weights_digest(
        four / "model.safetensors") != weights_digest(two / "model.safetensors")
    evaluate(str(shipped), episodes=1, n_envs=1, out_dir=tmp_path / "ev", videos=0,
             progress=False, report=False)
    info = json.loads((tmp_path / "ev" / "eval_info.json").read_text())
    assert info["config"]["policy_weights"] == weights_digest(four / "model.safetensors")
    notes: list[str] = []
    export_policy(four, shipped, tmp_path / "ev", log=notes.append)  # same weights: no flag
    assert notes == [] and json.loads((shipped / "eval_info.json").read_text()) == info
    assert f"| weights | `{info['config']['policy_weights']}` " in (shipped / "README.md"
                                                                    ).read_text()
    with pytest.raises(ValueError, match=r"ev/eval_info.json measured other weights \(shipped"):
        export_policy(two, tmp_path / "other", tmp_path / "ev")
    with pytest.raises(ValueError, match="measured other weights"):
        export_policy(two, tmp_path / "other", also_eval=[tmp_path / "ev"])
    assert not (tmp_path / "other").exists()
    with pytest.raises(ValueError, match=r"already holds another policy .* pass --replace"):
        export_policy(two, shipped)
    assert weights_digest(shipped / "model.safetensors") == info["config"]["policy_weights"]
    export_policy(two, shipped, replace=True)
    assert weights_digest(shipped / "model.safetensors") == weights_digest(
        two / "model.safetensors")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="holds other files, not an exported policy"):
        export_policy(two, mine, replace=True)
    assert (mine / "notes.txt").read_text() == "keep me"
    # an eval from before weights (and then software) were recorded: exported, with one line
    del info["config"]["policy_weights"], info["config"]["software"]
    (tmp_path / "ev" / "eval_info.json").write_text(json.dumps(info))
    export_policy(four, tmp_path / "old", tmp_path / "ev", log=notes.append)
    assert len(notes) == 1 and "names no weights" in notes[0]
    # the expert's eval went into a checkpoint's card with that same note
    evaluate("expert", episodes=1, n_envs=1, out_dir=tmp_path / "ev_expert", videos=0,
             progress=False, report=False)
    with pytest.raises(ValueError, match=r"ev_expert/eval_info.json measured expert, which "
                                         r"has no checkpoint weights, not .*step_0000004"):
        export_policy(four, tmp_path / "expert_card", tmp_path / "ev_expert")
    assert not (tmp_path / "expert_card").exists()


def test_frames_smaller_or_shaped_unlike_the_preset_get_a_note(dataset: Path, tmp_path: Path,
                                                                capsys) -> None:
    """48x64 demos trained at 60x80 were upscaled, and square ones stretched, in silence."""
    cpu = load_preset("cpu")
    assert frames_note((480, 640), cpu) is None and frames_note((60, 80), cpu) is None
    assert frames_note((76, 101), load_preset("seed")) is None  # 4:3 within rounding
    assert frames_note((48, 64), cpu) == (
        "so101-sim train: note: the dataset's frames are 48x64, smaller than preset cpu's 60x80 "
        "input: they are upscaled, which adds no detail; record at 60x80 or larger (so101-sim "
        "record --image-size, default 480x640), or train a preset made for 48x64 or less "
        "(cpu48)")
    assert "or train a preset" not in frames_note((30, 40), cpu)  # none is that small
    square = frames_note((480, 480), cpu)
    assert "another aspect ratio: every frame is stretched to 60x80" in square
    assert "--image-size 480x640" in square
    # train prints it: the 48x64 fixture demos on a tiny preset with 72x96 inputs
    big = shrunk_preset(tmp_path, "cpu", "big", [
        ("size = [24, 32]", "size = [72, 96]"), ("steps = 10000", "steps = 1"),
        ("down_dims = [48, 96, 192]", "down_dims = [16, 32, 64]")])
    train(dataset, tmp_path / "run", preset_name=str(big), progress=False)
    assert ("the dataset's frames are 48x64, smaller than preset big's 72x96 input"
            in capsys.readouterr().out)


def test_a_preset_variant_states_only_what_differs(tmp_path: Path) -> None:
    """`base = "cpu"`: the variant is cpu.toml with its own sections' keys on top."""
    cpu, small = load_preset("cpu"), load_preset("cpu48")
    assert small.image_size == (48, 64) and small.policy["crop_shape"] == (43, 58)
    assert small.train == cpu.train and small.image_normalize == cpu.image_normalize
    differ = {k for k in cpu.policy if cpu.policy[k] != small.policy[k]}
    assert differ == {"crop_shape"}
    loop = tmp_path / "loop.toml"
    loop.write_text('base = "loop.toml"\nname = "loop"\n')
    with pytest.raises(PresetError, match="leads back to itself"):
        load_preset(loop)
    typo = tmp_path / "typo.toml"
    typo.write_text('base = "cpuu"\nname = "typo"\n')
    with pytest.raises(PresetError, match=r"unknown preset 'cpuu' \(did you mean 'cpu'\?\); "):
        load_preset(typo)
    both = tmp_path / "both.toml"  # a variant of a Diffusion preset cannot turn into ACT
    both.write_text('base = "cpu"\nname = "both"\n[act]\nchunk_size = 32\n')
    with pytest.raises(PresetError, match=r"policy sections \['diffusion', 'act'\]; expected "
                                          "exactly one"):
        load_preset(both)


def test_act_trains_from_its_preset_and_evaluates(dataset: Path, tmp_path: Path) -> None:
    """An [act] preset trains lerobot's ACTPolicy: batches as LeRobotDataset gives them for
    ACT (one frame, no time axis; actions t..t+chunk-1), a checkpoint lerobot loads as ACT,
    a card that says so, and the harness runs it closed-loop."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tiny_policy import short_task

    from so101_sim.harness import evaluate
    from so101_sim.harness.export import export_policy
    from so101_sim.harness.policies.lerobot import LeRobotPolicy
    from so101_sim.train.checkpoint import load_checkpoint, read_train_info

    tiny_act = tiny_act_preset(tmp_path)
    preset = load_preset(tiny_act)
    assert preset.policy_type == "act" and preset.train.grad_clip_norm == 10.0
    cfg = make_config(preset, *policy_features(preset.image_size))
    ds = LeRobotDataset(DEFAULT_REPO_ID, root=dataset,
                        delta_timestamps={"action": [i / FPS for i in cfg.action_delta_indices]})
    demos = load_demos(ds, preset, None)
    assert len(demos.starts) == ds.meta.total_frames  # ACT drops no last frames
    end = int(ds.meta.episodes[0]["dataset_to_index"])
    idx = np.array([0, end - 3, end - 1])
    ours = gather_batch(demos, idx, cfg.observation_delta_indices, cfg.action_delta_indices)
    for row, i in enumerate(idx):
        item = ds[int(i)]
        for key in ("observation.state", "action", "action_is_pad"):
            assert torch.equal(ours[key][row], item[key]), key
    assert ours["observation.images.front"].shape == (3, 3, *preset.image_size)
    assert ours["action_is_pad"][2].sum() == cfg.chunk_size - 1  # last frame: only t real

    r = train(dataset, tmp_path / "run", preset_name=str(tiny_act), steps=2, progress=False)
    assert read_train_info(r.pretrained_dir)["policy_type"] == "act"
    loaded_cfg, trained, _, _ = load_checkpoint(r.pretrained_dir, expect_type="act")
    assert (loaded_cfg.chunk_size, loaded_cfg.n_action_steps) == (8, 4)
    shipped = export_policy(r.pretrained_dir, tmp_path / "shipped")
    card = (shipped / "README.md").read_text()
    assert card.startswith("# shipped: ACT for") and "lerobot `ACTPolicy`" in card
    # the shipped copy leaves out the VAE encoder and acts exactly as the trained model does
    slim_cfg, slim, _, _ = load_checkpoint(shipped, expect_type="act")
    assert trained.config.use_vae and not slim_cfg.use_vae
    full = trained.state_dict()
    vae = [k for k in full if k.startswith("model.vae_encoder")]
    assert vae and "ACT's VAE encoder" in card
    slim.load_state_dict({k: v for k, v in full.items() if k not in vae}, strict=True)
    with torch.no_grad():
        assert torch.equal(trained.predict_action_chunk(ours), slim.predict_action_chunk(ours))
    result = evaluate(LeRobotPolicy(r.pretrained_dir, log=lambda _: None),
                      task=short_task(tmp_path, max_steps=8), episodes=1, n_envs=1, videos=0,
                      image_size=SMALL, out_dir=tmp_path / "eval", progress=False, report=False,
                      log=lambda _: None)
    assert result["per_episode"][0]["steps"] == 8
    # the export without the VAE encoder still has the checkpoint's weights digest, so an
    # eval of either belongs on the card
    from so101_sim.harness.policies.checks import weights_digest

    assert weights_digest(shipped / "model.safetensors") == weights_digest(
        r.pretrained_dir / "model.safetensors")
    with pytest.raises(ValueError, match=r"--inference-steps \(num_inference_steps\) applies "
                                         "to diffusion policies; .* is a 'act' policy: drop it"):
        LeRobotPolicy(r.pretrained_dir, num_inference_steps=5, log=lambda _: None)


def test_close_windows_mark_each_close_of_its_own_episode() -> None:
    from so101_sim.train.demos import CloseWeighting, close_windows

    w = CloseWeighting(3.0, before=2, after=1)
    # episode 0 (frames 0-9): starts shut (not a close), opens, shuts at 5; reopens, shuts at 9.
    # episode 1 (frames 10-15): opens, shuts at 11; a dip to 20 is neither open nor closed.
    grip = np.array([0, 0, 45, 45, 45, 0, 0, 45, 45, 5, 45, 0, 0, 20, 0, 0], dtype=np.float32)
    ep_from = np.array([0] * 10 + [10] * 6)
    ep_to = np.array([10] * 10 + [16] * 6)
    mask = close_windows(grip, ep_from, ep_to, w)
    want = np.zeros(16, dtype=bool)
    want[3:7] = True    # close at 5: 2 before, 1 after
    want[7:10] = True   # close at 9: the window stops at its episode's end
    want[10:13] = True  # close at 11: the window starts at its episode's start
    np.testing.assert_array_equal(mask, want)


def test_oversample_closes_weights_the_draws_and_is_kept_on_resume(
        dataset: Path, tiny: Path, tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from so101_sim.train.demos import CloseWeighting, close_windows, sample_weights

    with pytest.raises(TrainError, match="expected a factor >= 1"):
        CloseWeighting(0.5)
    ds = LeRobotDataset("local/ds", root=dataset)
    demos = load_demos(ds, load_preset(str(tiny)), None)
    names = ds.meta.features["action"]["names"]
    assert sample_weights(demos, names, None) is None
    probs = sample_weights(demos, names, CloseWeighting(3.0))
    near = close_windows(demos.action[:, names.index("gripper.pos")], demos.episode_from,
                         demos.episode_to, CloseWeighting(3.0))[demos.starts]
    assert 0 < near.mean() < 0.6  # each demo grasps once: a window, not the whole episode
    assert probs.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(probs[near] / probs[~near].max(), 3.0)
    with pytest.raises(TrainError, match="needs one gripper action"):
        sample_weights(demos, [n.replace("gripper", "jaw") for n in names], CloseWeighting(3.0))

    fixed = {"progress": False, "threads": 1}
    run = train(dataset, tmp_path / "w", preset_name=str(tiny), steps=2, stop_at=1,
                oversample_closes=3.0, **fixed)
    info = json.loads((run.pretrained_dir / "so101_sim_train.json").read_text())
    assert info["oversample_closes"]["factor"] == 3.0
    with pytest.raises(TrainError, match="with the same value"):
        train(dataset, tmp_path / "w", preset_name=str(tiny), steps=2, resume=True, **fixed)
    done = train(dataset, tmp_path / "w", preset_name=str(tiny), steps=2, resume=True,
                 oversample_closes=3.0, **fixed)
    assert done.step == 2


def test_a_checkpoint_is_named_after_its_run(tmp_path: Path) -> None:
    """`train --out RUN` ends with RUN/pretrained_model: eval named every such policy
    "pretrained_model", in its summary line, its default --out folder and compare's tables."""
    from so101_sim.train.checkpoint import checkpoint_name

    run = tmp_path / "pp200"
    assert checkpoint_name(run / "pretrained_model") == "pp200"
    assert checkpoint_name(run / "checkpoints" / "step_0000500" / "pretrained_model") == \
        "pp200-step_0000500"
    assert checkpoint_name(tmp_path / "shipped_policy") == "shipped_policy"

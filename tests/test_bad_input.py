"""Bad input gets a clear error naming the thing, never a wrong answer or a hang."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from so101_sim.sim import PickPlaceEnv
from so101_sim.tasks import TaskSpecError, load_task

TASK = Path(__file__).parents[1] / "envs" / "pick_place.toml"


@pytest.fixture(scope="module")
def env() -> PickPlaceEnv:
    e = PickPlaceEnv(obs_type="state")
    yield e
    e.close()


@pytest.mark.parametrize(("options", "message"), [
    ({"cube_pose": [np.nan, 0.05, 0.0]}, r"cube_pose=\[nan, 0.05, 0.0\] contains NaN or inf"),
    ({"cube_pose": [0.2, np.inf, 0.0]}, "contains NaN or inf"),
    ({"target_pos": [0.2, np.nan]}, "target_pos=.* contains NaN or inf"),
    ({"cube_pose": [0.2, 0.05]}, r"cube_pose has shape \(2,\); expected \(3,\)"),
    ({"cube_pose": "here"}, "cube_pose='here' is not numeric"),
    ({"cube_pose": [2.0, 0.05, 0.0]}, "cube_pose x=2, y=0.05 is off the table; expected x in"),
    ({"target_pos": [0.2, -0.9]}, "target_pos x=0.2, y=-0.9 is off the table"),
    ({"cube_pose": [0.0, 0.0, 0.0]}, "is inside the robot's base"),
    ({"cube_xyz": [0.2, 0.0]}, r"unknown reset options \['cube_xyz'\]"),
])
def test_bad_reset_options_are_refused(env: PickPlaceEnv, options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        env.reset(seed=0, options=options)


def test_valid_reset_options_still_pin_the_episode(env: PickPlaceEnv) -> None:
    _, info = env.reset(seed=0, options={"cube_pose": [0.22, 0.06, 10.0],
                                         "target_pos": [0.2, -0.1]})
    np.testing.assert_allclose(info["cube_pose"], [0.22, 0.06, 10.0])
    np.testing.assert_allclose(info["target_pos"], [0.2, -0.1])


def test_mujoco_instability_ends_the_episode_as_sim_unstable(env: PickPlaceEnv, tmp_path: Path,
                                                            monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the cwd
    obs, _ = env.reset(seed=0)
    adr = env.model.jnt_dofadr[env.model.joint("cube").id]
    env.data.qvel[adr:adr + 3] = 1e12  # a blow-up: MuJoCo warns and resets the state itself
    _, _, terminated, truncated, info = env.step(obs["agent_pos"])
    assert terminated and not truncated
    assert info["failure_mode"] == "sim_unstable"


@pytest.mark.parametrize(("old", "new", "message"), [
    ("physics_substeps = 8", "physics_substeps = 100000000",
     "physics_substeps = 100000000 is too large; expected at most 1000"),
    ("max_steps = 300", "max_steps = 5000000000000", "max_steps = 5000000000000 is too large"),
])
def test_task_numbers_that_would_hang_are_refused(tmp_path: Path, old: str, new: str,
                                                  message: str) -> None:
    path = tmp_path / "t.toml"
    text = TASK.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    with pytest.raises(TaskSpecError, match=message):
        load_task(path)


def test_non_utf8_task_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(TASK.read_text().replace("Pick up", "Pick up caf\u00e9").encode("latin-1"))
    with pytest.raises(TaskSpecError, match=r"latin1\.toml: not UTF-8 text"):
        load_task(path)


def test_record_of_a_task_at_another_fps_says_what_to_change(tmp_path: Path) -> None:
    # the message named neither the task file nor the fix; and nothing is written
    path = tmp_path / "t15.toml"
    text = TASK.read_text()
    assert "\nfps = 30 " in text
    path.write_text(text.replace("\nfps = 30 ", "\nfps = 15 "))
    r = _cli("record", "--task", str(path), "--episodes", "1", "--out", str(tmp_path / "d"))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"--task {path}: its fps is 15; expected 30" in r.stderr, r.stderr
    assert "set fps = 30 in the task file" in r.stderr, r.stderr
    assert not (tmp_path / "d").exists()


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "so101-sim"
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", **(env or {})})


def test_corrupt_eval_config_is_named(tmp_path: Path) -> None:
    out = tmp_path / "ev"
    assert _cli("eval", "--policy", "expert", "--episodes", "1", "--n-envs", "1",
                "--videos", "0", "--out", str(out)).returncode == 0
    (out / "eval_config.json").write_text('{"policy": "exp')
    r = _cli("eval", "--policy", "expert", "--episodes", "1", "--n-envs", "1", "--videos", "0",
             "--out", str(out), "--resume")
    assert r.returncode == 2
    assert "eval_config.json is corrupt" in r.stderr and "Traceback" not in r.stderr


def test_unwritable_out_is_one_line(tmp_path: Path) -> None:
    # /sys refuses new folders even to root; elsewhere a read-only folder does the same
    target = "/sys/so101_sim_test" if os.path.isdir("/sys") else str(tmp_path / "ro" / "x")
    r = _cli("eval", "--policy", "expert", "--episodes", "1", "--out", target)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "permission denied; choose a folder you own" in r.stderr


def test_unusable_mujoco_gl_lists_what_works() -> None:
    code = "import so101_sim.sim.env"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "MUJOCO_GL": "nonsense"})
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("RuntimeError: MUJOCO_GL='nonsense' cannot be used")
    assert "backends that work here" in last or "no headless backend works" in last
    r = _cli("eval", "--policy", "expert", "--episodes", "1", "--videos", "1",
             env={"MUJOCO_GL": "nonsense"})
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "MUJOCO_GL='nonsense' cannot be used" in r.stderr


def test_corrupt_train_log_is_skipped_by_export(tmp_path: Path, capsys) -> None:
    from so101_sim.harness.export import loss_curve

    log = tmp_path / "train_log.jsonl"
    rows = [{"step": i, "loss": 1.0 / i, "lr": 1e-4, "samples_per_s": 10} for i in (1, 2, 3)]
    log.write_text(json.dumps(rows[0]) + "\n\x00\x00garbage\n" + json.dumps(rows[1]) + "\n"
                   + json.dumps(rows[2])[:20])
    assert [r["step"] for r in loss_curve(log)] == [1, 2]
    assert "train_log.jsonl: skipped unreadable line 2" in capsys.readouterr().out


def test_gl_backend_line_is_printed_once_not_per_worker(tmp_path: Path) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_policy import make_tiny_diffusion_checkpoint, short_task

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "tiny")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    r = subprocess.run([str(Path(sys.executable).parent / "so101-sim"), "eval", "--policy",
                        str(ckpt), "--task", str(short_task(tmp_path, 10)), "--episodes", "2",
                        "--n-envs", "2", "--videos", "0", "--out", str(tmp_path / "ev")],
                       capture_output=True, text=True, timeout=300,
                       env={**env, "HF_HUB_OFFLINE": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stderr.count("MUJOCO_GL not set; rendering with") == 1, r.stderr[-2000:]


def test_faithful_with_another_image_size_is_refused(capsys, tmp_path: Path) -> None:
    """`--faithful --image-size 60x80` cannot be both: refused before anything runs, where
    the size used to win silently. The recorded size itself is no contradiction."""
    from so101_sim.cli import main
    from so101_sim.harness.frames import choose_rendering
    from so101_sim.harness.policies import PolicyInfo

    out = tmp_path / "eval"
    policy = str(Path(__file__).parents[1] / "policy" / "pick_place_diffusion")
    assert main(["eval", "--policy", policy, "--faithful", "--image-size", "60x80",
                 "--episodes", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--faithful renders at the training data's 480x640, but --image-size asks for " \
           "60x80; drop one of them" in err
    assert not out.exists()
    info = PolicyInfo(name="p", cameras=("front",), image_size=(60, 80),
                      train_image_size=(480, 640))
    assert choose_rendering(info, (480, 640), faithful=True).label.startswith("faithful")


def test_faithful_for_a_policy_without_cameras_says_it_changes_nothing() -> None:
    """A state-only policy (the expert) has no training frames to render faithfully: the run's
    images line says --faithful changed nothing, where it used to read as if it had run."""
    from so101_sim.harness.frames import choose_rendering
    from so101_sim.harness.policies import PolicyInfo

    info = PolicyInfo(name="expert", cameras=(), image_size=None)
    assert choose_rendering(info, None, faithful=True).label == (
        "no camera input (state only; --faithful changes nothing); videos rendered at 240x320")
    assert choose_rendering(info, None).label == (
        "no camera input (state only); videos rendered at 240x320")


def test_resume_without_out_is_refused(tmp_path, capsys, monkeypatch):
    """Without --out each run gets a new timestamped folder: --resume there resumed nothing
    and silently ran a fresh evaluation."""
    from so101_sim.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", "expert", "--episodes", "1", "--resume"]) == 2
    assert "--resume given without --out" in capsys.readouterr().err
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("argv", [
    ["demo", "--steps", "0"],
    ["demo", "--steps", "-1"],
    ["eval", "--policy", "expert", "--threads", "0"],
    ["eval", "--policy", "expert", "--policy-batch", "0"],
    ["train", "--dataset", "d", "--out", "o", "--threads", "-2"],
    ["demo", "--seed", "-1"],
    ["record", "--out", "o", "--episodes", "0"],
    ["record", "--out", "o", "--episodes", "1", "--workers", "0"],
    ["record", "--out", "o", "--episodes", "1", "--checkpoint-every", "0"],
    ["record", "--out", "o", "--episodes", "1", "--seed-start", "-1"],
    ["eval", "--policy", "expert", "--episodes", "0"],
    ["eval", "--policy", "expert", "--n-envs", "0"],
    ["eval", "--policy", "expert", "--videos", "-1"],
    ["eval", "--policy", "expert", "--seed-start", "-1"],
    ["eval", "--policy", "expert", "--against", "r", "--max-episodes", "0"],
    ["eval", "--policy", "expert", "--n-action-steps", "0"],
    ["eval", "--policy", "expert", "--inference-steps", "0"],
    ["curve", "run", "--episodes", "0"],
    ["curve", "run", "--n-envs", "-1"],
    ["curve", "run", "--every", "-3"],
    ["train", "--dataset", "d", "--out", "o", "--steps", "0"],
    ["train", "--dataset", "d", "--out", "o", "--batch-size", "0"],
    ["train", "--dataset", "d", "--out", "o", "--stop-at", "-1"],
    ["replay", "d", "--episode", "-1"],
    ["explain", "--dataset", "d", "--episode", "-1"],
    ["explain", "--dataset", "d", "--k", "-1"],
    ["explain", "--dataset", "d", "--seed", "-1"],
])
def test_counts_below_one_are_refused_by_the_parser(argv: list[str], capsys) -> None:
    """A count below 1 used to write an empty demo mp4 (--steps 0), fail inside numpy
    (--steps -1) or torch (train --threads -2) after minutes of frame decoding, or mean
    'default' in silence (eval --threads 0); a negative demo seed failed in Gymnasium. train
    --steps 0 and curve --every -3 were refused after start-up, under another prefix.
    Others were caught by the library under its own names (`n_episodes=0`, `n_envs=0`)
    rather than the flag the user typed."""
    from so101_sim.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    flag, value = argv[-2:]
    low = 0 if flag in ("--seed", "--seed-start", "--videos", "--every", "--episode", "--k") else 1
    assert f"argument {flag}: {value} is invalid; expected an integer >= {low}" in \
        capsys.readouterr().err


@pytest.mark.parametrize("value", ["front,top", "front,front", ","])
def test_bad_cameras_are_named_in_the_flags_syntax(value: str, capsys) -> None:
    """record --cameras front,top answered with Python tuples: cameras=('front', 'top')."""
    from so101_sim.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["record", "--out", "o", "--episodes", "1", "--cameras", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert (f"argument --cameras: {value!r} is invalid; expected distinct names from front, "
            "side, wrist, e.g. front,side") in err
    assert "(" not in err.splitlines()[-1].split("--cameras")[1]


@pytest.mark.parametrize(("argv", "hint"), [
    (["replay", "--dataset", "d", "--episode", "0"],
     "DATASET is positional in `so101-sim replay`, with no flag: so101-sim replay d --episode 0"),
    (["curve", "--run", "r"], "RUN is positional in `so101-sim curve`, with no flag: "
                              "so101-sim curve r"),
    (["curve", "--run=r", "--episodes", "2"], "RUN is positional in `so101-sim curve`, with "
                                              "no flag: so101-sim curve r --episodes 2"),
    (["export", "--checkpoint", "c", "--out", "o"],
     "CHECKPOINT is positional in `so101-sim export`, with no flag: so101-sim export c --out o"),
    (["compare", "a", "b", "--outt", "c"], "did you mean --out?"),
    (["eval", "--polcy", "p", "--out", "o"], "--polcy; did you mean --policy?"),
    (["train", "--datset", "d", "--out", "o"], "--datset; did you mean --dataset?"),
    (["record", "--episodes", "1", "--out", "o", "extra"],
     "`so101-sim record --help` lists its arguments"),
])
def test_an_unknown_argument_is_named_under_its_commands_usage(argv: list[str], hint: str,
                                                               capsys) -> None:
    """`replay --dataset D` (train's and explain's spelling) was answered with the top-level
    usage, which lists commands and none of replay's arguments; `eval --polcy P` only with
    "the following arguments are required: --policy"."""
    from so101_sim.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: so101-sim {argv[0]} ")
    assert f"so101-sim {argv[0]}: error: unrecognized arguments: " in err
    assert hint in err


@pytest.mark.parametrize(("argv", "line"), [
    (["eval", "--policy", "expert", "--out", ""],
     "argument --out: '' is empty; expected a value (an unset shell variable expands to ''); "
     "or leave --out out for its default"),
    (["train", "--dataset", "d", "--out", ""], "argument --out: '' is empty; expected a value "
                                               "(an unset shell variable expands to '')"),
    (["demo", "--out="], "argument --out: '' is empty"),
    (["curve", ""], "argument RUN: '' is empty"),
    (["export", "c", "--eval", "e", "--eval", ""], "argument --eval: '' is empty"),
])
def test_an_empty_value_is_refused_by_name(argv: list[str], line: str, capsys) -> None:
    """`--out "$OUT"` with OUT unset: eval, train and demo wrote into the current folder (an
    empty path is '.'), beside whatever was there; explain took its default."""
    from so101_sim.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert f"so101-sim {argv[0]}: error: {line}" in capsys.readouterr().err


def test_a_curve_refuses_training_seeds_by_its_flag(capsys) -> None:
    """curve has no --allow-train-seeds: the library's hint to pass it was wrong there."""
    from so101_sim.cli import main

    with pytest.raises(SystemExit):
        main(["curve", "run", "--seed-start", "5"])
    err = capsys.readouterr().err
    assert "argument --seed-start: 5 is a training seed" in err and "allow" not in err


def test_ray_connect_timeout_without_an_address_is_refused(capsys, tmp_path: Path) -> None:
    """The timeout is how long to wait for the cluster at --ray-address; without one it was
    ignored in silence."""
    from so101_sim.cli import main

    out = tmp_path / "eval"
    assert main(["eval", "--policy", "expert", "--episodes", "1", "--ray-connect-timeout", "5",
                 "--out", str(out)]) == 2
    assert "--ray-connect-timeout 5 only applies with --ray-address" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(("choice", "message"), [
    ({"steps": [3]}, r"--steps 3: .* has no checkpoint there \(saved steps: 2, 4\)"),
    ({"every": -1}, "every=-1 is invalid; expected 0 .* or a step interval >= 1"),
    ({"every": 3}, "--every 3: no checkpoint of .* is at a multiple of 3"),
    ({"every": 4, "steps": [2]}, "no checkpoint .* at a multiple of 4 among --steps"),
])
def test_curve_choice_of_no_saved_checkpoint_is_refused(tmp_path: Path, choice: dict,
                                                        message: str) -> None:
    """`curve --steps 3` on a run saved at steps 2 and 4 printed the curve of the others as
    if step 3 were done; --every -1 meant 'all'. Refused before any lock or folder."""
    from so101_sim.harness.curve import evaluate_curve

    for step in (2, 4):
        model = tmp_path / "checkpoints" / f"step_{step:07d}" / "pretrained_model"
        model.mkdir(parents=True)
        (model / "model.safetensors").write_bytes(b"")  # only its presence is read
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(ValueError, match=message):
        evaluate_curve(tmp_path, **choice)
    assert sorted(tmp_path.rglob("*")) == before


def test_eval_into_a_checkpoint_folder_is_refused(tmp_path: Path) -> None:
    """`--out` the policy's own folder wrote eval_info.json over the one its export keeps
    for its card."""
    from so101_sim.harness import evaluate

    folder = tmp_path / "policy"
    folder.mkdir()
    (folder / "model.safetensors").write_bytes(b"weights")
    (folder / "eval_info.json").write_text('{"recorded": true}')
    with pytest.raises(ValueError, match=r"holds a policy checkpoint .* choose another --out"):
        evaluate("expert", episodes=1, n_envs=1, out_dir=folder, videos=0, progress=False)
    from so101_sim.record.demo import run_demo

    with pytest.raises(ValueError, match=r"holds a policy checkpoint .*; the demo's video"):
        run_demo(folder, steps=1)
    assert sorted(p.name for p in folder.iterdir()) == ["eval_info.json", "model.safetensors"]
    assert (folder / "eval_info.json").read_text() == '{"recorded": true}'


def test_an_out_that_holds_a_run_is_refused_before_the_policy_loads(tmp_path: Path, capsys,
                                                                  monkeypatch) -> None:
    """A forgotten --resume was said only after the policy had loaded and the render
    self-check had run (5-10 s with a checkpoint)."""
    import so101_sim.harness as harness
    from so101_sim.cli import main

    def no_load(*args, **kwargs):
        raise AssertionError("the policy loaded before --out was checked")

    monkeypatch.setattr(harness, "load_policy", no_load)
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "episodes.jsonl").write_text("")
    assert main(["eval", "--policy", "expert", "--out", str(folder)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"so101-sim eval: error: {folder} already holds an evaluation (episodes.jsonl); pass "
        "--resume to finish it, or choose another --out"]


def test_eval_or_train_into_a_dataset_folder_is_refused(tmp_path: Path) -> None:
    """`--out` a LeRobotDataset (say, --out the --dataset) put the run's videos/, report or
    checkpoints, or the demo's video and images, among the dataset's files."""
    from so101_sim.harness import evaluate
    from so101_sim.record.demo import run_demo
    from so101_sim.train import TrainError, train

    folder = tmp_path / "ds"
    (folder / "meta").mkdir(parents=True)
    (folder / "meta" / "info.json").write_text("{}")
    with pytest.raises(ValueError, match=r"is a LeRobotDataset \(meta/info.json\); an eval"):
        evaluate("expert", episodes=1, n_envs=1, out_dir=folder, videos=0, progress=False)
    with pytest.raises(TrainError, match=r"is a LeRobotDataset \(meta/info.json\); a run"):
        train(folder, folder, steps=1, progress=False)
    with pytest.raises(ValueError, match=r"is a LeRobotDataset \(meta/info.json\); the demo's"):
        run_demo(folder, steps=1)
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) == [
        "meta", "meta/info.json"]


def test_bf16_on_a_cpu_without_it_says_it_is_slow(monkeypatch) -> None:
    """bf16 autocast on an AVX2 CPU is emulated: 14x slower per forward, in silence before."""
    from so101_sim.harness.policies.lerobot import LeRobotPolicy
    from so101_sim.utils import devices

    monkeypatch.setattr(devices, "cpu_has_fast_bf16", lambda: False)
    assert "bf16 autocast is emulated" in devices.slow_bf16_note("bf16", "cpu")
    assert devices.slow_bf16_note("fp32", "cpu") is devices.slow_bf16_note("bf16", "cuda") is None
    messages: list[str] = []
    LeRobotPolicy(Path(__file__).parents[1] / "policy" / "pick_place_diffusion",
                  precision="bf16", log=messages.append)
    assert sum("bf16 autocast is emulated" in m for m in messages) == 1
    monkeypatch.setattr(devices, "cpu_has_fast_bf16", lambda: True)
    assert devices.slow_bf16_note("bf16", "cpu") is None


def test_export_takes_any_checkpoint_folder_and_names_a_damaged_file(tmp_path: Path,
                                                                     monkeypatch) -> None:
    """A checkpoint outside a run's checkpoints/step_N/ with a short path ended in an
    IndexError; a torn safetensors file in a SafetensorError traceback."""
    import shutil

    from so101_sim.harness.export import export_policy

    monkeypatch.chdir(tmp_path)
    shutil.copytree(Path(__file__).parents[1] / "policy" / "pick_place_diffusion", "p")
    assert (export_policy(Path("p"), Path("out")) / "README.md").is_file()
    data = Path("p/model.safetensors").read_bytes()
    Path("p/model.safetensors").write_bytes(data[:100_000])
    with pytest.raises(ValueError, match=r"p/model.safetensors cannot be read as safetensors"):
        export_policy(Path("p"), Path("out2"))
    Path("p/model.safetensors").write_bytes(data)
    Path("out/model.safetensors").write_bytes(b"torn")  # a damaged export: --replace fixes it
    with pytest.raises(ValueError, match=r"--out out holds a damaged export .* pass --replace"):
        export_policy(Path("p"), Path("out"))
    assert (export_policy(Path("p"), Path("out"), replace=True) / "README.md").is_file()
    norm = next(Path("p").glob("policy_preprocessor_*.safetensors"))
    norm.write_bytes(b"garbage")
    with pytest.raises(ValueError, match=f"{norm} cannot be read as safetensors"):
        export_policy(Path("p"), Path("out2"))
    assert not Path("out2").exists()


def test_a_damaged_dataset_or_init_checkpoint_is_one_line(tmp_path: Path) -> None:
    """A torn parquet file came out of `datasets` as a DatasetGenerationError traceback, and
    torn --init-from weights as a SafetensorError one."""
    import shutil

    from so101_sim.dataset.reader import NotADatasetError, open_lerobot_dataset
    from so101_sim.record import record
    from so101_sim.train import TrainError, train

    ds = tmp_path / "ds"
    record(ds, 1, image_size=(48, 64), progress=False)
    ckpt = tmp_path / "ckpt"
    shutil.copytree(Path(__file__).parents[1] / "policy" / "pick_place_diffusion", ckpt)
    weights = (ckpt / "model.safetensors").read_bytes()
    (ckpt / "model.safetensors").write_bytes(weights[: len(weights) // 2])
    with pytest.raises(TrainError, match=r"--init-from: .*model.safetensors cannot be read as "
                                         "safetensors"):
        train(ds, tmp_path / "run", steps=1, progress=False, init_from=ckpt)
    part = next((ds / "data").rglob("*.parquet"))
    part.write_bytes(part.read_bytes()[:300])
    with pytest.raises(NotADatasetError, match=r"cannot be read as a LeRobotDataset \(Arrow"):
        open_lerobot_dataset(ds)
    with pytest.raises(TrainError, match=r"a file in it is damaged \(copied in part, or "
                                         r"edited\): copy or record the dataset again"):
        train(ds, tmp_path / "run2", steps=1, progress=False)


@pytest.mark.parametrize("argv", [["demo", "--steps", "2"], ["demo", "--grid", "2x2"],
                                  ["export", "policy/pick_place_diffusion"]])
def test_out_that_is_a_file_is_one_line(argv: list[str], tmp_path: Path, capsys,
                                        monkeypatch) -> None:
    """demo made a FileExistsError traceback; export called the file 'other files' and
    printed it without the 'error:' the other commands print."""
    from so101_sim.cli import main

    monkeypatch.chdir(Path(__file__).parents[1])
    target = tmp_path / "afile"
    target.write_text("mine")
    assert main([*argv, "--out", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"so101-sim {argv[0]}: error: ")  # as every other command's errors
    assert f"{target} is a file; expected a folder" in err
    assert target.read_text() == "mine"


@pytest.mark.parametrize("argv", [["train", "--dataset", "no_such_dataset", "--out", "run"],
                                  ["export", "no_such_checkpoint", "--out", "shipped"]])
def test_train_and_export_errors_say_error(argv: list[str], tmp_path: Path, capsys,
                                           monkeypatch) -> None:
    """train's and export's own errors lacked the 'error:' every other command prints."""
    from so101_sim.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"so101-sim {argv[0]}: error: ") and err.count("\n") == 1, err
    assert argv[1] in err


def test_env_workers_are_capped_by_the_available_memory(tmp_path: Path, monkeypatch) -> None:
    """--n-envs 200 on a small machine started 200 workers of ~120 MB each: an OOM kill.
    The run takes what fits, says so in one line, and its outcomes are the same."""
    from so101_sim.harness import evaluate
    from so101_sim.utils import devices

    assert devices.available_mb() > 0  # read from /proc/meminfo here
    lines: list[str] = []
    monkeypatch.setattr(devices, "available_mb", lambda: 1024 + 2 * devices.WORKER_MB)
    assert devices.workers_that_fit(2, lines.append) == 2 and lines == []
    info = evaluate("expert", episodes=3, n_envs=3, out_dir=tmp_path / "capped", videos=0,
                    progress=False, log=lines.append)
    assert info["config"]["workers"]["workers"] == 2
    assert [m for m in lines if "env workers would take" in m] == [
        f"so101-sim eval: 3 env workers would take about "
        f"{3 * devices.WORKER_MB / 1024:.1f} GB ({devices.WORKER_MB} MB each) and "
        f"{(1024 + 2 * devices.WORKER_MB) / 1024:.1f} GB is available: running 2 (the actions "
        "of each seed are the same for any --n-envs)"]
    monkeypatch.undo()
    again = evaluate("expert", episodes=3, n_envs=3, out_dir=tmp_path / "all", videos=0,
                     progress=False, log=lambda _: None)
    assert again["config"]["workers"]["workers"] == 3
    assert all(e["actions_sha"] for e in info["per_episode"])
    assert [e["actions_sha"] for e in info["per_episode"]] == [
        e["actions_sha"] for e in again["per_episode"]]


def test_ctrl_c_while_a_command_starts_is_one_line(monkeypatch, capsys) -> None:
    """Ctrl-C during a command's imports or loading printed a KeyboardInterrupt traceback."""
    import so101_sim.harness.compare as compare
    from so101_sim.cli import main

    def loading(*_: object, **__: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(compare, "compare_runs", loading)
    assert main(["compare", "a", "b"]) == 130
    assert capsys.readouterr().err == "so101-sim compare: interrupted\n"

    import so101_sim.harness.curve as curve

    monkeypatch.setattr(curve, "evaluate_curve", loading)  # mid-run: what is kept, what next
    assert main(["curve", "somerun"]) == 130
    assert capsys.readouterr().err == ("so101-sim curve: interrupted; every finished episode "
                                       "is kept under somerun: run the same command again to "
                                       "finish the curve\n")


def _run_with_checkpoints(run: Path, steps: list[int]) -> Path:
    for step in steps:
        d = run / "checkpoints" / f"step_{step:07d}" / "pretrained_model"
        d.mkdir(parents=True)
        (d / "model.safetensors").write_bytes(b"")
    return run


@pytest.mark.parametrize("typed, said", [
    ("nowhere", "does not exist; pass the --out folder"),
    ("RUN/checkpoints/step_0000004/pretrained_model",
     "is one checkpoint of the run RUN (did you mean `so101-sim curve RUN`?); pass"),
    ("RUN/checkpoints/step_0000004", "is one checkpoint of the run RUN (did you mean"),
    (".", "holds no checkpoints/step_*/pretrained_model; pass the --out folder"),
])
def test_curve_of_what_is_not_a_run_says_what_it_is(typed: str, said: str, tmp_path: Path,
                                                     monkeypatch, capsys) -> None:
    """A missing path was said to "hold no checkpoints"; a checkpoint given for its run was
    not named as one."""
    from so101_sim.cli import main

    _run_with_checkpoints(tmp_path / "RUN", [4])
    monkeypatch.chdir(tmp_path)
    assert main(["curve", typed]) == 2
    assert f"so101-sim curve: error: {typed} {said}" in capsys.readouterr().err


def test_a_ctrl_c_lost_in_a_gc_callback_still_stops_the_curve(tmp_path, monkeypatch,
                                                              lose_a_ctrl_c) -> None:
    """Python drops an exception raised in a weakref callback: a Ctrl-C landing there ran the
    rest of the curve. Now the curve stops before the next checkpoint."""
    import signal

    import so101_sim.harness.curve as curve

    run = _run_with_checkpoints(tmp_path / "run", [100, 200, 300])
    evaluated = []
    before = signal.getsignal(signal.SIGINT)

    def first_one_signals(run_: Path, task: str, step: int, *_: object) -> None:
        evaluated.append(step)
        if step == 100:
            lose_a_ctrl_c()

    monkeypatch.setattr(curve, "_evaluate_step", first_one_signals)
    with pytest.raises(KeyboardInterrupt):
        curve.evaluate_curve(run, episodes=2)
    assert evaluated == [100]
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_sigterm_ends_a_curve_with_its_line(tmp_path, monkeypatch, capsys) -> None:
    import signal

    import so101_sim.harness.curve as curve
    from so101_sim.cli import main

    run = _run_with_checkpoints(tmp_path / "run", [100, 200])
    evaluated = []
    before = signal.getsignal(signal.SIGTERM)  # another test's handler may be in place

    def terminated(run_: Path, task: str, step: int, *_: object) -> None:
        evaluated.append(step)
        os.kill(os.getpid(), signal.SIGTERM)
        sum(range(1000))

    monkeypatch.setattr(curve, "_evaluate_step", terminated)
    assert main(["curve", str(run), "--episodes", "2"]) == 130
    assert evaluated == [100]
    assert "so101-sim curve: interrupted; every finished episode is kept" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is before  # restored


def test_every_cli_option_says_what_it_does() -> None:
    """`--help` of each command lists every option with its meaning (four had none)."""
    import argparse

    from so101_sim.cli.parser import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    bare = [f"{name} {a.option_strings or a.dest}" for name, p in sub.choices.items()
            for a in p._actions if not a.help and "--help" not in a.option_strings]
    assert bare == []


def test_every_cli_default_is_in_its_help() -> None:
    """An option that has a default says what it is (`eval --videos` wrote 2 mp4s unasked,
    `curve --episodes` ran 32 seeds, `record --workers` used 1 worker: none said so)."""
    from so101_sim.cli.parser import build_parsers

    unsaid = [f"{name} {a.option_strings[0]}={a.default!r}"
              for name, p in build_parsers()[1].items() for a in p._actions
              if a.option_strings and a.default not in (None, False, [], "==SUPPRESS==")
              and "default" not in a.help]
    assert unsaid == []


def test_the_typical_run_in_the_top_level_help_parses(tmp_path: Path) -> None:
    """Each command `so101-sim --help` shows as a typical run is accepted as written, and its
    eval names the policy train leaves in RUN (it named lerobot-train's checkpoints/last/,
    which train does not write)."""
    from so101_sim.cli.parser import build_parser
    from so101_sim.train.trainer import finish

    parser = build_parser()
    lines = [x.split()[1:] for x in parser.epilog.splitlines() if x.startswith("  so101-sim ")]
    assert [x[0] for x in lines] == ["record", "train", "eval", "compare"]
    for argv in lines:
        assert parser.parse_args(argv).command == argv[0]
    run = _run_with_checkpoints(tmp_path / "RUN", [4])
    finish(run, run / "checkpoints" / "step_0000004", keep_frame_cache=False)
    policy = parser.parse_args(lines[2]).policy
    assert (tmp_path / policy / "model.safetensors").is_file(), policy


@pytest.mark.parametrize("typed, meant", [
    ("RUN/checkpoints/last/pretrained_model", ["RUN/pretrained_model",
                                               "RUN/checkpoints/step_0000008/pretrained_model"]),
    ("RUN", ["RUN/pretrained_model"]),
    ("RUN/checkpoints/step_0000004", ["RUN/checkpoints/step_0000004/pretrained_model"]),
    ("elsewhere/pretrained_model", []),
])
def test_a_policy_path_next_to_a_policy_names_it(typed: str, meant: list[str], tmp_path: Path,
                                                 capsys, monkeypatch) -> None:
    """lerobot-train's habit (checkpoints/last/pretrained_model), the run folder itself or a
    step folder given to eval or export: the error names the policy folder that is there."""
    from so101_sim.cli import main

    run = _run_with_checkpoints(tmp_path / "RUN", [4, 8])
    for model in (*run.glob("checkpoints/*/pretrained_model"), run / "pretrained_model"):
        model.mkdir(exist_ok=True)
        (model / "config.json").write_text("{}")
        (model / "so101_sim_train.json").write_text("{}")  # what export also needs
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", typed, "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert f"policy checkpoint {typed} " in err
    if meant:
        assert f"did you mean --policy {' or --policy '.join(meant)}? " in err
    else:
        assert "did you mean" not in err
    assert main(["export", typed]) == 2  # export says the same
    err = capsys.readouterr().err
    assert f"{typed} is not a so101-sim checkpoint" in err
    assert (f"did you mean {' or '.join(meant)}?" in err) if meant else ("did you mean" not in err)


def test_a_lerobot_train_run_folder_as_policy_names_its_last_checkpoint(
        tmp_path: Path, capsys, monkeypatch) -> None:
    """lerobot-train's outputs/train/RUN given to --policy: its checkpoints/last (a link to the
    latest numbered step) holds the policy."""
    from so101_sim.cli import main

    model = tmp_path / "outputs/train/pp/checkpoints/005000/pretrained_model"
    model.mkdir(parents=True)
    (model / "config.json").write_text("{}")
    (model.parents[1] / "last").symlink_to("005000")
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", "outputs/train/pp", "--episodes", "1"]) == 2
    assert ("policy checkpoint outputs/train/pp has no config.json; did you mean --policy "
            "outputs/train/pp/checkpoints/last/pretrained_model?") in capsys.readouterr().err
    assert main(["export", "outputs/train/pp"]) == 2  # not one export takes: not suggested
    err = capsys.readouterr().err
    assert "is not a so101-sim checkpoint" in err and "did you mean" not in err


def test_a_folder_of_policies_given_as_policy_names_them(tmp_path: Path, capsys,
                                                        monkeypatch) -> None:
    """`--policy policy` (the folder the shipped ones live in) only said "has no config.json";
    so did lerobot's CLIs, with a traceback. Both now name the policies in it."""
    from so101_sim.cli import main
    from so101_sim.policy_frames import folder_problem

    monkeypatch.chdir(tmp_path)
    for name in ("b_policy", "a_policy"):
        (tmp_path / "policies" / name).mkdir(parents=True)
        (tmp_path / "policies" / name / "config.json").write_text("{}")
    (tmp_path / "policies" / "presets").mkdir()  # not a policy: not named
    assert main(["eval", "--policy", "policies", "--episodes", "1"]) == 2
    assert ("policy checkpoint policies has no config.json; did you mean --policy "
            "policies/a_policy or --policy policies/b_policy? expected") in capsys.readouterr().err
    problem = folder_problem(["lerobot-eval", "--policy.path=policies"])
    assert problem is not None and problem.text == (
        "--policy.path=policies holds no config.json, so lerobot cannot load a policy from it; "
        "did you mean --policy.path=policies/a_policy or --policy.path=policies/b_policy?")


def test_a_dataset_or_an_evaluation_given_as_policy_says_what_it_is(tmp_path: Path, capsys,
                                                                   monkeypatch) -> None:
    """`eval --policy DATA` or `--policy EVAL` (an eval's --out) only said "has no
    config.json"; now the error says what the folder is and which command takes it."""
    from so101_sim.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "data" / "meta").mkdir(parents=True)
    (tmp_path / "data" / "meta" / "info.json").write_text("{}")
    ev = tmp_path / "ev"
    ev.mkdir()
    (ev / "eval_config.json").write_text("{}")
    assert main(["eval", "--policy", "data", "--episodes", "1"]) == 2
    assert ("policy checkpoint data has no config.json; it is a LeRobotDataset, which `so101-sim "
            "train --dataset data --out RUN` trains a policy on; expected a lerobot checkpoint"
            ) in capsys.readouterr().err
    assert main(["eval", "--policy", "ev", "--episodes", "1"]) == 2  # interrupted: no info
    said = "(the --out of `so101-sim eval`, which `so101-sim compare` reads); expected"
    assert f"policy checkpoint ev has no config.json; it is an evaluation {said}" in \
        capsys.readouterr().err
    (ev / "eval_info.json").write_text(json.dumps(
        {"config": {"policy_details": {"checkpoint": "policy/pick_place_diffusion"}}}))
    assert main(["eval", "--policy", "ev", "--episodes", "1"]) == 2
    assert ("policy checkpoint ev has no config.json; it is an evaluation of the policy "
            f"policy/pick_place_diffusion {said}") in capsys.readouterr().err
    assert main(["export", "ev", "--out", "shipped"]) == 2  # export says it too
    assert ("ev is not a so101-sim checkpoint (needs model.safetensors and so101_sim_train.json)"
            "; it is an evaluation of the policy policy/pick_place_diffusion (the --out") in \
        capsys.readouterr().err


@pytest.mark.parametrize("typed", ["policy/pick_place_diffusion", "pick_place_diffusion"])
def test_the_shipped_policy_typed_outside_the_checkout_is_named(typed: str, tmp_path: Path,
                                                                capsys, monkeypatch) -> None:
    """README's `--policy policy/pick_place_diffusion`, run from another folder: the error
    names where the shipped policy is."""
    from so101_sim.cli import main
    from so101_sim.utils.paths import shipped_policy_dir

    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", typed, "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert f"policy checkpoint {typed} not found; did you mean --policy {shipped_policy_dir()}?" \
        in err
    assert main(["eval", "--policy", "policy/no_such_policy", "--episodes", "1"]) == 2
    assert "did you mean" not in capsys.readouterr().err


def test_a_hub_repo_id_as_policy_says_how_to_fetch_it(tmp_path: Path, capsys,
                                                      monkeypatch) -> None:
    """lerobot's `--policy.path=lerobot/diffusion_pusht` habit: so101-sim reads folders only
    (nothing downloads at run time), and the error says how to get one."""
    from so101_sim.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", "someone/so101_policy", "--episodes", "1"]) == 2
    assert ("'someone/so101_policy' looks like a Hugging Face Hub repo id, and so101-sim reads "
            "local folders only: fetch it once with `hf download someone/so101_policy "
            "--local-dir so101_policy` and pass --policy so101_policy") in capsys.readouterr().err
    for command in (["train"], ["explain"]):  # --dataset USER/REPO: a dataset repo
        assert main([*command, "--dataset", "someone/so101_demos", "--out", "o"]) == 2
        assert ("'someone/so101_demos' looks like a Hugging Face Hub repo id, and so101-sim "
                "reads local folders only: fetch it once with `hf download someone/so101_demos "
                "--repo-type dataset --local-dir so101_demos` and pass --dataset so101_demos"
                ) in capsys.readouterr().err, command
    (tmp_path / "pretrained_model").mkdir()  # run from inside a run: both lines
    (tmp_path / "pretrained_model" / "config.json").write_text("{}")
    assert main(["eval", "--policy", "someone/so101_policy", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean --policy pretrained_model? " in err
    assert "; 'someone/so101_policy' looks like a Hugging Face Hub repo id" in err
    (tmp_path / "runs").mkdir()  # a missing folder in a local one is a local path
    for local in ("runs/missing", "a/b/c", "/abs/path"):
        assert main(["eval", "--policy", local, "--episodes", "1"]) == 2
        assert "Hub repo id" not in capsys.readouterr().err, local


def test_init_from_a_run_folder_suggests_init_from_not_policy(tmp_path: Path,
                                                              monkeypatch) -> None:
    """`train --init-from RUN` (the run folder, not its pretrained_model) got eval's hint:
    "did you mean --policy RUN/pretrained_model? ... or --policy expert"."""
    from so101_sim.train.checkpoint import init_weights_from

    (tmp_path / "run" / "pretrained_model").mkdir(parents=True)
    (tmp_path / "run" / "pretrained_model" / "config.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError) as caught:
        init_weights_from(object(), "run")  # the files are checked before the policy is read
    assert str(caught.value).startswith("policy checkpoint run has no config.json; did you mean "
                                        "--init-from run/pretrained_model? expected a lerobot ")
    assert "--policy" not in str(caught.value)


def test_an_export_onto_its_own_checkpoint_is_refused_and_the_card_kept(tmp_path: Path,
                                                                       monkeypatch) -> None:
    """`so101-sim export policy/pick_place_diffusion --eval E` (its --out defaults to that same
    folder) rewrote the shipped card from a folder with no run beside it: the training log,
    the success curve and the measured rate were gone."""
    import shutil

    from so101_sim.cli import main

    monkeypatch.chdir(tmp_path)
    shutil.copytree(Path(__file__).parents[1] / "policy" / "pick_place_diffusion", "p")
    card = Path("p/README.md").read_text()
    from so101_sim.harness.export import export_policy

    for out, said in (("p", "--out p is the checkpoint itself; "),
                      ("./p/", "--out p is the checkpoint itself; "),
                      ("p/copy", "--out p/copy lies inside the checkpoint p; ")):
        with pytest.raises(ValueError, match=re.escape(said)):
            export_policy(Path("p"), Path(out))
    assert main(["export", "p", "--out", "p"]) == 2
    assert Path("p/README.md").read_text() == card and not Path("p/copy").exists()


def test_an_export_of_a_run_folder_names_its_checkpoint_not_the_out(tmp_path: Path,
                                                                     capsys, monkeypatch) -> None:
    """`so101-sim export RUN --out RUN/shipped` said only that --out lay inside "the
    checkpoint" RUN, which is no checkpoint: the error is the folder, and its policy is named."""
    from so101_sim.cli import main

    model = tmp_path / "run" / "pretrained_model"
    model.mkdir(parents=True)
    for name in ("config.json", "so101_sim_train.json"):
        (model / name).write_text("{}")
    (model / "model.safetensors").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    assert main(["export", "run", "--out", "run/shipped"]) == 2
    err = capsys.readouterr().err
    assert ("so101-sim export: error: run is not a so101-sim checkpoint (needs model.safetensors "
            "and so101_sim_train.json); did you mean run/pretrained_model?") in err
    assert "lies inside" not in err and not Path("run/shipped").exists()


def test_explain_refuses_an_out_that_is_a_dataset_or_a_checkpoint(tmp_path: Path) -> None:
    """`explain --out DATA` wrote explain.html and explain.json among a dataset's files."""
    from so101_sim.explain import explain
    from so101_sim.explain.errors import ExplainError

    data = tmp_path / "data"
    (data / "meta").mkdir(parents=True)
    (data / "meta" / "info.json").write_text("{}")
    with pytest.raises(ExplainError, match=r"--out .*data is a LeRobotDataset \(meta/info.json\)"
                                           r"; the page .* choose another --out"):
        explain(data, None, out=data)  # refused before the dataset is opened
    ckpt = Path(__file__).parents[1] / "policy" / "pick_place_diffusion"
    with pytest.raises(ExplainError, match=r"holds a policy checkpoint"):
        explain(data, ckpt, out=ckpt)
    assert sorted(p.name for p in data.iterdir()) == ["meta"]
    assert not (ckpt / "explain.html").exists()


def test_an_export_leaves_out_folders_inside_the_checkpoint_and_says_so(
        tmp_path: Path, monkeypatch) -> None:
    """An eval written inside a checkpoint folder (`eval --out CKPT/ev`) shipped with its
    export, videos and all: a checkpoint holds files only."""
    import shutil

    from so101_sim.harness.export import export_policy

    monkeypatch.chdir(tmp_path)
    shutil.copytree(Path(__file__).parents[1] / "policy" / "pick_place_diffusion", "p")
    (tmp_path / "p" / "ev" / "videos").mkdir(parents=True)
    (tmp_path / "p" / "ev" / "videos" / "seed_0.mp4").write_bytes(b"\0" * 1000)
    notes: list[str] = []
    out = export_policy(Path("p"), Path("out"), log=notes.append)
    assert not (out / "ev").exists() and (out / "config.json").is_file()
    assert notes == ["so101-sim export: note: p holds folders ['ev'], which no checkpoint has (an "
                     "eval's --out inside it, say); the export leaves them out"]
    assert sorted(f.name for f in out.iterdir()) == sorted(
        f.name for f in Path("p").iterdir() if f.name != "ev")


@pytest.mark.parametrize(("name", "value"), [
    ("episodes", 2.5), ("episodes", True), ("episodes", "3"), ("episodes", [100_000]),
    ("n_envs", 2.5), ("threads", 0), ("max_retries", -1), ("checkpoint_every", 0),
    ("worker_timeout_s", 0), ("worker_timeout_s", float("nan")), ("image_size", (0, 5)),
])
def test_evaluates_python_arguments_are_named_before_any_worker_starts(name, value, tmp_path):
    """The Python API checked less than the CLI's flags: `episodes=2.5` ended in a TypeError
    from range(), `True` ran one episode, `n_envs=2.5` and `threads=0` ran, `max_retries=-1`
    ran with no rerun, `worker_timeout_s=0` failed every episode three times ("no reply within
    0 s"), and `image_size=(0, 5)` came back as a worker that could not start."""
    from so101_sim.harness import evaluate

    with pytest.raises(ValueError, match=rf"^{name}=.* is invalid; expected "):
        evaluate("expert", **{"episodes": 1, name: value}, out_dir=tmp_path / "run",
                 progress=False, report=False, log=lambda line: None)
    assert not (tmp_path / "run").exists()  # refused before the folder was made


@pytest.mark.parametrize(("name", "value"), [("n_episodes", 2.5), ("n_episodes", 0),
                                             ("seed_start", 1.5), ("seed_start", -1)])
def test_records_python_counts_are_named(name, value, tmp_path):
    from so101_sim.record import record

    with pytest.raises(ValueError, match=rf"^{name}={value} is invalid; expected an integer"):
        record(tmp_path / "data", **{"n_episodes": 1, name: value})
    assert not (tmp_path / "data").exists()


@pytest.mark.parametrize(("name", "value"), [
    ("steps", 2.5), ("steps", True), ("batch_size", 2.5), ("threads", 0), ("stop_at", 2.5)])
def test_trains_python_counts_are_named(name, value, tmp_path):
    """`train(steps=2.5)` trained 2 steps, `steps=True` one, `batch_size=2.5` a batch of 2,
    `threads=0` meant "adaptive", and `stop_at=2.5` was "outside 1..--steps (2)"."""
    from so101_sim.train import TrainError, train

    with pytest.raises(TrainError, match=rf"^{name}={value} is invalid; expected an integer"):
        train(tmp_path / "data", tmp_path / "run", **{"steps": 2, name: value})
    assert not (tmp_path / "run").exists()

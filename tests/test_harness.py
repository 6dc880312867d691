"""The rollout harness (`so101-sim eval`): determinism across K, outputs, resume, bad input.

Real env workers, real rendering, real files. The diffusion checkpoint is tiny and untrained
(tests/tiny_policy.py) and episodes are cut short, so these are about mechanics, not skill.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import signal
import sys
import threading
import time
from importlib import metadata
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from so101_sim.cli import main
from so101_sim.harness import ChunkRequest, PolicyInfo, evaluate, expert_policy, load_policy
from so101_sim.harness.policies.lerobot import LeRobotPolicy
from so101_sim.utils.versions import cpu_description

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import make_tiny_diffusion_checkpoint, short_task

SEEDS = 8
RESULT_KEYS = ("seed", "success", "failure_mode", "steps", "sum_reward", "actions_sha")


def _outcomes(result: dict) -> list[tuple]:
    return [tuple(e[k] for k in RESULT_KEYS) for e in result["per_episode"]]


def _quiet(**kw):
    return {"progress": False, "log": lambda _: None, **kw}


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    return make_tiny_diffusion_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny",
                                          input_size=(48, 64), dataset_image_size=(96, 128))


@pytest.fixture(scope="module")
def short(tmp_path_factory) -> Path:
    return short_task(tmp_path_factory.mktemp("task"), max_steps=16)  # two chunks of 8


@pytest.fixture(scope="module")
def expert_k1(tmp_path_factory) -> dict:
    return evaluate("expert", episodes=SEEDS, n_envs=1, videos=0, report=False,
                    out_dir=tmp_path_factory.mktemp("expert_k1") / "run", **_quiet())


# ------------------------------------------------------------------------ determinism
def test_expert_results_do_not_depend_on_n_envs(expert_k1, tmp_path):
    k4 = evaluate("expert", episodes=SEEDS, n_envs=4, videos=0, report=False,
                  out_dir=tmp_path / "k4", **_quiet())
    assert _outcomes(k4) == _outcomes(expert_k1)
    assert all(e["success"] for e in k4["per_episode"])


def test_diffusion_results_do_not_depend_on_n_envs(tiny_ckpt, short, tmp_path):
    policy = LeRobotPolicy(tiny_ckpt, log=lambda _: None)
    assert policy.batch_size == 8, "padded batches are position-independent here"
    logs: dict[int, list[str]] = {1: [], 4: []}
    runs = {k: evaluate(policy, task=str(short), episodes=SEEDS, n_envs=k, videos=0,
                        report=False, out_dir=tmp_path / f"k{k}", **_quiet(log=logs[k].append))
            for k in (1, 4)}
    assert _outcomes(runs[1]) == _outcomes(runs[4])
    for k in (1, 4):  # the padding is named once, with the --n-envs that avoids it
        assert sum("the rest is padding" in line and "--n-envs 8" in line
                   for line in logs[k]) == 1, logs[k]
    said = {k: next(x for x in logs[k] if "the rest is padding" in x) for k in (1, 4)}
    assert "1 env fills at most 1 of each 8-row" in said[1]  # not "1 env(s) fill"
    assert "4 envs fill at most 4 of each 8-row" in said[4]
    # every chunk is one row whatever the envs; one env pads each forward with 7 copies
    rows = {k: r["config"]["policy_rows"] for k, r in runs.items()}
    assert rows[1]["used"] == rows[4]["used"] > 0
    assert rows[1]["computed"] == 8 * rows[1]["used"]
    assert rows[4]["computed"] % 8 == 0 and rows[4]["computed"] < rows[1]["computed"]
    shas = {e["actions_sha"] for e in runs[1]["per_episode"]}
    assert len(shas) == SEEDS, "each seed samples its own diffusion noise"
    assert "faithful" in runs[1]["config"]["images"]


def test_pipelined_forwards_keep_results_per_seed(tiny_ckpt, short, tmp_path):
    """More envs than rows per forward: some envs step while the policy runs for others, and
    forwards go out in whatever order envs ask; every seed's outcome stays the same."""
    policy = LeRobotPolicy(tiny_ckpt, batch_size=2, log=lambda _: None)
    runs = {k: evaluate(policy, task=str(short), episodes=SEEDS, n_envs=k, videos=0,
                        report=False, out_dir=tmp_path / f"k{k}", **_quiet())
            for k in (2, 3, 5)}
    assert _outcomes(runs[2]) == _outcomes(runs[5])  # actions bit for bit, too
    assert _outcomes(runs[3]) == _outcomes(runs[5])
    assert len({e["actions_sha"] for e in runs[5]["per_episode"]}) == SEEDS
    # two forwards ran at once on driver threads (harness.forwards) wherever there were more
    # envs than rows per forward (2, or 1 where this CPU's batches are not row-independent):
    # with 3 envs and 2 rows, the odd row's short forward ran beside a full one, not after it.
    for k, run in runs.items():
        assert run["config"]["forwards_in_flight"] == (2 if k > policy.batch_size else 1), k
        rows = run["config"]["policy_rows"]
        assert rows["computed"] % policy.batch_size == 0 and rows["computed"] >= rows["used"]
    policy.concurrent_forwards = False
    one = evaluate(policy, task=str(short), episodes=SEEDS, n_envs=5, videos=0, report=False,
                   out_dir=tmp_path / "one", **_quiet())
    assert one["config"]["forwards_in_flight"] == 1
    assert _outcomes(one) == _outcomes(runs[5])
    import torch  # a torch policy's run records which kernels computed its actions

    assert one["config"]["cpu_isa"] == torch.backends.cpu.get_cpu_capability()


def test_padded_rows_do_not_depend_on_batch_mates(tiny_ckpt):
    """Why the adapter pads: on CPU a row's bits can change with the batch size."""
    policy = LeRobotPolicy(tiny_ckpt, log=lambda _: None)
    rng = np.random.default_rng(0)
    reqs = [ChunkRequest(i, 100000 + i, [{
        "agent_pos": rng.uniform(-50, 50, 6).astype(np.float32),
        "pixels": {c: rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
                   for c in ("front", "side")}} for _ in range(2)]) for i in range(4)]

    def chunks(batch_size: int, rows: list) -> np.ndarray:
        policy.batch_size = batch_size
        for r in rows:
            policy.start_episode(r.slot, r.seed)
        return policy.predict_chunks(rows)

    padded_alone = chunks(8, reqs[:1])
    padded_together = chunks(8, reqs)
    assert np.array_equal(padded_alone[0], padded_together[0])
    assert np.array_equal(chunks(1, reqs[:1])[0], chunks(1, reqs[2:3] + reqs[:1])[1])


# ------------------------------------------------------------------------ outputs and resume
REDUCED = ("reduced: rendered at 180x240 (mesh detail of the recorded 640 px width), "
           "resize_frames to 60x80; vs the faithful 480x640: mean |diff| 0.40, p99 8, max 32 "
           "grey levels over 8 frames")  # what the default path says of the shipped policy


def test_a_pipe_in_a_value_stays_inside_its_table_cell(tmp_path):
    """The images line of the default path, "mean |diff| 0.40", split report.md's table row;
    and the wall-time row gave --n-envs (16 envs) where one episode ran on one worker."""
    import re

    from so101_sim.harness.report import write_report
    from so101_sim.harness.results import check_record

    out = tmp_path / "run"
    assert main(["eval", "--policy", "expert", "--episodes", "1", "--n-envs", "16", "--videos",
                 "0", "--image-size", "48x64", "--out", str(out)]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    records = [check_record(json.loads(x), "episodes.jsonl")
               for x in (out / "episodes.jsonl").read_text().splitlines()]
    info["config"]["images"] = REDUCED
    md = write_report(out, info, records).read_text()
    table = [x for x in md.splitlines() if x.startswith("|")]
    assert len(table) > 8
    for row in table:  # "| key | value |": 2 cells, whatever the value holds
        assert len(re.split(r"(?<!\\)\|", row)) == 4, row
    assert "| images | reduced: rendered at 180x240" in md and "mean \\|diff\\| 0.40" in md
    assert "| env workers | local backend, 1 worker on 1 node |" in md  # not "1 workers"
    wall = [x for x in md.splitlines() if x.startswith("| wall time")]
    assert len(wall) == 1 and wall[0].endswith("s/episode, 1 env |"), wall  # not --n-envs 16


def test_outputs_videos_report_and_resume(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["eval", "--policy", "expert", "--episodes", "5", "--n-envs", "2",
                 "--videos", "1", "--image-size", "48x64", "--out", str(out)])
    assert code == 0
    summary = capsys.readouterr().out
    assert "success 5/5 = 100.0% (95% CI" in summary
    info = json.loads((out / "eval_info.json").read_text())
    agg = info["aggregated"]
    for key in ("pc_success", "success_ci95", "n_episodes", "failure_modes", "avg_sum_reward",
                "avg_max_reward", "avg_episode_len", "eval_s", "eval_ep_s"):
        assert key in agg, key
    assert set(agg["time"]) >= {"physics_s", "render_s", "policy_s"}
    assert agg["n_episodes"] == 5 and agg["pc_success"] == 100.0
    assert agg["success_ci95"][0] < 100.0 == agg["success_ci95"][1]
    lines = (out / "episodes.jsonl").read_text().splitlines()
    assert sorted(json.loads(x)["seed"] for x in lines) == list(range(100000, 100005))
    video = out / "videos" / "episode_0000_seed100000.mp4"
    frames = imageio.mimread(video, memtest=False)
    assert len(frames) > 100 and frames[0].shape[0] >= 240
    assert not list((out / "videos").glob("*.part.mp4"))
    report = (out / "report.md").read_text()
    assert "report.png" in report and (out / "report.png").stat().st_size > 10_000
    assert "Wilson" in report
    assert f"mujoco {metadata.version('mujoco')}" in report and cpu_description() in report

    # A killed run: three episodes on disk, the last line torn mid-write.
    (out / "episodes.jsonl").write_text("\n".join(lines[:3]) + "\n" + lines[3][:25])
    (out / "eval_info.json").unlink()

    def resume(episodes: int, videos: int, done: int) -> tuple[str, dict]:
        """`eval --resume`: it says how many seeds it kept; the first ones are the run's."""
        assert main(["eval", "--policy", "expert", "--episodes", str(episodes), "--n-envs",
                     "2", "--videos", str(videos), "--image-size", "48x64", "--out", str(out),
                     "--resume"]) == 0
        said = capsys.readouterr().out
        assert f"({done} done, {episodes - done} to run)" in said
        again = json.loads((out / "eval_info.json").read_text())
        assert [e["seed"] for e in again["per_episode"]] == list(range(100000,
                                                                       100000 + episodes))
        assert _strip_times(again["per_episode"][:5]) == _strip_times(info["per_episode"])
        assert again["aggregated"]["n_episodes"] == episodes
        return said, again

    said, again = resume(5, 1, done=3)
    assert "note:" not in said and "earlier_setups" not in again["config"]  # the same setup
    # More episodes on --resume extend the run: the first five are kept, two more run.
    resume(7, 0, done=5)
    # Episodes finished with another torch (as if upgraded since): a resume says so and
    # eval_info keeps that setup; the next resume still knows.
    config = json.loads((out / "eval_config.json").read_text())
    now = config["setups"][-1]
    then = {**now, "software": {**now["software"], "torch": "0.0.1"}}
    (out / "eval_config.json").write_text(json.dumps({**config, "setups": [then]}))
    for n in (8, 9):
        said, again = resume(n, 0, done=n - 1)
        assert (f"note: the episodes already in {out} ran with another setup (torch 0.0.1 vs "
                f"{now['software']['torch']}, then vs now)") in said
        assert again["config"]["earlier_setups"] == [then]
        assert again["config"]["software"] == now["software"]
    with pytest.raises(ValueError, match="episodes: 9 there, 5 now"):
        evaluate("expert", episodes=5, out_dir=out, resume=True, **_quiet())

    with pytest.raises(ValueError, match="--resume"):
        evaluate("expert", episodes=5, out_dir=out, **_quiet())
    with pytest.raises(ValueError, match="seed_start: 100000 there, 100100 now"):
        evaluate("expert", episodes=5, seed_start=100100, out_dir=out, resume=True, **_quiet())
    with pytest.raises(ValueError, match="policy_fingerprint"):
        evaluate(_HoldStill(), episodes=5, out_dir=out, resume=True, **_quiet())


def test_the_resume_command_of_a_run_without_out_names_its_folder(tmp_path, capsys,
                                                                  monkeypatch):
    """Without --out a run gets a new timestamped folder; the command that continues it (the
    disk-full hint, the Ctrl-C line) carries --out with that folder, and it resumes there.
    That command lasts as long as main(): afterwards the Python API's hints are its own."""
    import shlex

    import so101_sim.harness.runner as runner
    from so101_sim.utils.disk import DiskFullError, note_default_out, resume_command

    seen = []

    def noting(folder):  # the command as it stands while the run writes `folder`
        note_default_out(folder)
        seen.append(resume_command())

    monkeypatch.setattr(runner, "note_default_out", noting)
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--policy", "expert", "--episodes", "1", "--n-envs", "1",
                 "--videos", "0", "--image-size", "48x64"]) == 0
    (folder,) = (tmp_path / "outputs" / "eval").iterdir()
    assert resume_command() is None
    assert "run the same command with --resume" in str(DiskFullError("episodes", folder))
    argv = shlex.split(seen[0])
    assert argv[-3:] == ["--out", str(folder.relative_to(tmp_path)), "--resume"]
    capsys.readouterr()
    assert main([*argv[1:-3], "--episodes", "2", *argv[-3:]]) == 0
    assert "(1 done, 1 to run)" in capsys.readouterr().out
    assert list((tmp_path / "outputs" / "eval").iterdir()) == [folder]


def _strip_times(episodes: list[dict]) -> list[dict]:
    return [{k: v for k, v in e.items() if k not in ("seconds", "video")} for e in episodes]


# ------------------------------------------------------------------------ user policies
class _HoldStill:
    """A user policy: looks at the front camera, holds the arm where it is, 4 steps a chunk."""

    info = PolicyInfo(name="hold", cameras=("front",), image_size=(48, 64), n_obs_steps=2,
                      n_action_steps=4, fingerprint="hold-v1")

    def __init__(self, bad_seed: int | None = None) -> None:
        self.bad_seed = bad_seed
        self.seen: list[tuple] = []

    def start_episode(self, slot: int, seed: int) -> None:
        pass

    def predict_chunks(self, requests):
        out = []
        for r in requests:
            self.seen.append((len(r.history), r.history[-1]["pixels"]["front"].shape))
            a = np.repeat(r.history[-1]["agent_pos"][None], 4, axis=0)
            if r.seed == self.bad_seed:
                a[:] = np.nan
            out.append(a)
        return np.stack(out)


def test_user_policy_protocol(short, tmp_path):
    policy = _HoldStill()
    res = evaluate(policy, task=str(short), episodes=2, n_envs=2, videos=0, report=False,
                   out_dir=tmp_path / "run", **_quiet())
    assert {(2, (48, 64, 3))} == set(policy.seen)
    assert [e["failure_mode"] for e in res["per_episode"]] == ["never_grasped"] * 2
    assert "direct" in res["config"]["images"]


def test_a_ctrl_c_lost_in_a_gc_callback_still_stops_eval(short, tmp_path, lose_a_ctrl_c):
    """Python drops an exception raised in a weakref callback: a Ctrl-C landing there ran
    every episode. Now the loop stops at its next turn, with the finished episodes kept."""

    class LosesACtrlC(_HoldStill):
        def start_episode(self, slot: int, seed: int) -> None:
            if seed == 100_001:  # the second episode: the first one is finished
                lose_a_ctrl_c()

    before = signal.getsignal(signal.SIGINT)
    assert before is signal.default_int_handler  # what eval takes over (else leaves alone)
    with pytest.raises(KeyboardInterrupt):
        evaluate(LosesACtrlC(), task=str(short), episodes=4, n_envs=1, videos=0,
                 report=False, out_dir=tmp_path / "run", **_quiet())
    lines = (tmp_path / "run" / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["seed"] for x in lines] == [100_000]
    assert signal.getsignal(signal.SIGINT) is before  # restored


TERMINATES = '''
import os, signal
from so101_sim.harness import expert_policy


class Terminates:
    """The expert; SIGTERM to this process as the second seed starts."""

    def __init__(self, task):
        self.inner = expert_policy(task)
        self.info = self.inner.info

    def start_episode(self, slot, seed):
        if seed == 100_001:
            os.kill(os.getpid(), signal.SIGTERM)
        self.inner.start_episode(slot, seed)

    def predict_chunks(self, requests):
        return self.inner.predict_chunks(requests)


def make(task):
    return Terminates(task)
'''


def test_sigterm_ends_an_eval_with_its_resume_line(short, tmp_path):
    """`timeout 600 so101-sim eval ...` or a cancelled CI job sends SIGTERM: eval died without
    a word (rc -15) while record, train and curve said what was kept; now it ends as Ctrl-C
    does, with the command that resumes, and that command finishes the run."""
    (tmp_path / "terminates.py").write_text(TERMINATES)
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "HF_HUB_OFFLINE": "1",
           "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "so101_sim.cli", "eval", "--policy", "terminates:make",
            "--task", str(short), "--episodes", "3", "--n-envs", "1", "--videos", "0",
            "--image-size", "48x64", "--out", str(out)]
    import subprocess

    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300,
                       start_new_session=True)
    assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("so101-sim eval: interrupted; every finished episode is in "
                           "episodes.jsonl (finish with: ")
    lines = (out / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["seed"] for x in lines] == [100_000]
    again = last.split("(finish with: ", 1)[1].removesuffix(")")
    assert again.endswith(" --resume")
    policy = load_policy("expert", task=str(short))  # the resumed run: no SIGTERM this time
    res = evaluate(policy, task=str(short), episodes=3, n_envs=1, videos=0, report=False,
                   out_dir=out, resume=True, image_size=(48, 64), **_quiet())
    assert [e["seed"] for e in res["per_episode"]] == [100_000, 100_001, 100_002]


class _CountThreads(_HoldStill):
    """Notes torch's CPU thread count at every forward."""

    def predict_chunks(self, requests):
        import torch

        self.threads = getattr(self, "threads", set()) | {torch.get_num_threads()}
        return super().predict_chunks(requests)


def test_policy_threads_default_to_half_the_cores_and_are_restored(short, tmp_path):
    import torch

    from so101_sim.utils.devices import cpu_count, eval_policy_threads

    before = torch.get_num_threads()
    assert eval_policy_threads() == max(1, cpu_count() // 2)
    for asked, expected in ((None, eval_policy_threads()), (1, 1), (3, 3)):
        policy = _CountThreads()
        evaluate(policy, task=str(short), episodes=2, n_envs=2, videos=0, report=False,
                 out_dir=tmp_path / f"run{asked}", threads=asked, **_quiet())
        assert policy.threads == {expected}
        assert torch.get_num_threads() == before  # the caller's setting comes back


def test_more_policy_threads_than_cores_get_one_line(short, tmp_path, monkeypatch):
    """`eval --threads N` above the cores: kept as asked, with the line that says the cost."""
    from so101_sim.utils import devices

    monkeypatch.setattr(devices, "cpu_count", lambda: 1)
    said: list[str] = []
    policy = _CountThreads()
    evaluate(policy, task=str(short), episodes=2, n_envs=2, videos=0, report=False,
             out_dir=tmp_path / "run", threads=2, progress=False, log=said.append)
    assert policy.threads == {2}
    assert [s for s in said if "--threads" in s] == [
        "so101-sim eval: note: --threads 2 is more than the 1 CPU core this process can use, so "
        "torch's threads wait on each other (a training step took 34x as long with 8 threads on "
        "2 cores); --threads 1 or fewer, or leave it out"]


def test_policy_error_is_retried_then_reported(short, tmp_path):
    with pytest.raises(RuntimeError, match=r"(?s)seed 100001 failed 3 times.*NaN"):
        evaluate(_HoldStill(bad_seed=100001), task=str(short), episodes=3, n_envs=2,
                 videos=0, report=False, out_dir=tmp_path / "run", **_quiet())
    lines = [json.loads(x) for x in (tmp_path / "run" / "episodes.jsonl").read_text()
             .splitlines()]
    assert [x["seed"] for x in lines if x["status"] == "error"] == [100001] * 3


def test_dead_worker_episode_is_marked_error_and_rerun(expert_k1, tmp_path):
    out = tmp_path / "run"
    killed: list[int] = []

    def killer() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            f = out / "episodes.jsonl"
            if f.exists() and f.read_text().count("\n") >= 1:
                workers = [p for p in mp.active_children() if p.name.startswith("so101-eval")]
                if workers:
                    os.kill(workers[0].pid, signal.SIGKILL)
                    killed.append(workers[0].pid)
            time.sleep(0.01)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    res = evaluate("expert", episodes=SEEDS, n_envs=2, videos=0, report=False, out_dir=out,
                   **_quiet())
    thread.join()
    assert killed, "no worker was killed"
    lines = [json.loads(x) for x in (out / "episodes.jsonl").read_text().splitlines()]
    errors = [x for x in lines if x["status"] == "error"]
    assert errors and "died" in errors[0]["error"]
    assert _outcomes(res) == _outcomes(expert_k1)


# ------------------------------------------------------------------------ bad input
def test_training_seeds_are_refused(tmp_path):
    with pytest.raises(ValueError, match="--allow-train-seeds"):
        evaluate("expert", episodes=2, seed_start=0, out_dir=tmp_path / "run", **_quiet())


def test_unknown_task_and_policy_are_named(tmp_path, capsys):
    with pytest.raises(ValueError, match="no_such_task"):
        evaluate("expert", task="no_such_task", episodes=2, out_dir=tmp_path / "a", **_quiet())
    assert main(["eval", "--policy", str(tmp_path / "nothing"), "--episodes", "1",
                 "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "nothing not found" in err and "config.json" in err


def _broken_copy(src: Path, dst: Path, edit) -> Path:
    shutil.copytree(src, dst)
    edit(dst)
    return dst


def test_bad_checkpoints_are_named(tiny_ckpt, tmp_path):
    def corrupt_config(d: Path) -> None:
        (d / "config.json").write_text('{"type": "diffusion", ')

    def truncate_weights(d: Path) -> None:
        data = (d / "model.safetensors").read_bytes()
        (d / "model.safetensors").write_bytes(data[: len(data) // 3])

    def edit_features(key: str, value):
        def edit(d: Path) -> None:
            cfg = json.loads((d / "config.json").read_text())
            feats = cfg["input_features"]
            if value is None:
                feats[key.replace("side", "laptop")] = feats.pop(key)
            else:
                feats[key]["shape"] = value
            (d / "config.json").write_text(json.dumps(cfg))
        return edit

    cases = [
        (corrupt_config, ValueError, "config.json is not a lerobot policy config"),
        (truncate_weights, RuntimeError, "model.safetensors could not be loaded"),
        (edit_features("observation.images.side", None), ValueError, "camera 'laptop'"),
        (edit_features("observation.state", [7]), ValueError, r"observation.state of shape \(7,\)"),
        (lambda d: (d / "policy_preprocessor.json").unlink(), FileNotFoundError,
         "no policy_preprocessor.json"),
    ]
    for n, (edit, exc, pattern) in enumerate(cases):
        bad = _broken_copy(tiny_ckpt, tmp_path / f"bad{n}", edit)
        with pytest.raises(exc, match=pattern):
            load_policy(bad)


def test_inference_overrides_are_checked(tiny_ckpt):
    messages: list[str] = []
    policy = LeRobotPolicy(tiny_ckpt, n_action_steps=4, batch_size=1, log=messages.append)
    assert policy.info.n_action_steps == 4
    assert any("n_action_steps=8; using 4 as asked" in m for m in messages)
    with pytest.raises(ValueError, match=r"n_action_steps=20 is invalid.*1\.\.15"):
        LeRobotPolicy(tiny_ckpt, n_action_steps=20, log=messages.append)
    with pytest.raises(ValueError, match=r"--temporal-ensemble nan is invalid"):
        LeRobotPolicy(tiny_ckpt, temporal_ensemble_coeff=float("nan"), log=messages.append)
    with pytest.raises(ValueError, match=r"--policy-batch \(batch_size\) applies to lerobot "
                                         "checkpoints, not to --policy expert"):
        load_policy("expert", batch_size=4)
    with pytest.raises(ValueError, match=r"--policy-batch \(batch_size\), --precision "
                                         r"\(precision\) apply to lerobot checkpoints, not to "
                                         "--policy mypkg.policies:make; drop them"):
        load_policy("mypkg.policies:make", batch_size=4, precision="bf16")  # was ignored


def test_worker_side_resize_gives_the_driver_resize_bit_for_bit():
    """Frames resized in the env worker (small replies) equal the driver's resize of the full
    render, and the driver passes them through untouched."""
    from so101_sim.harness.env_worker import EnvWorkerConfig
    from so101_sim.harness.frames import Rendering, to_policy_obs
    from so101_sim.tasks import load_task

    rendering = Rendering((96, 128), (48, 64), "test")
    obs = {}
    for resize_to in (None, (48, 64)):
        worker = EnvWorkerConfig(task=load_task("pick_place"), render_size=(96, 128),
                                 cameras=("front", "side"), env_state=False, n_obs_steps=2,
                                 resize_to=resize_to)()
        try:
            obs[resize_to] = worker.reset(100_003)["history"][0]
        finally:
            worker.close()
    full, small = obs[None], obs[(48, 64)]
    assert full["pixels"]["front"].shape == (96, 128, 3)
    assert small["pixels"]["front"].shape == (48, 64, 3)
    driver = to_policy_obs(full, rendering)
    for cam in ("front", "side"):
        assert np.array_equal(driver["pixels"][cam], small["pixels"][cam])
    assert to_policy_obs(small, rendering)["pixels"] is small["pixels"]


def test_bf16_forwards_are_close_to_fp32_and_named(tiny_ckpt):
    """--precision bf16: same seeds give nearby chunks, and the run says which precision ran."""
    rng = np.random.default_rng(1)
    reqs = [ChunkRequest(i, 100000 + i, [{
        "agent_pos": rng.uniform(-50, 50, 6).astype(np.float32),
        "pixels": {c: rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
                   for c in ("front", "side")}} for _ in range(2)]) for i in range(3)]
    chunks = {}
    for precision in ("fp32", "bf16"):
        policy = LeRobotPolicy(tiny_ckpt, precision=precision, log=lambda _: None)
        for r in reqs:
            policy.start_episode(r.slot, r.seed)
        chunks[precision] = policy.predict_chunks(reqs)
        assert chunks[precision].dtype == np.float32
        assert ("precision" in policy.info.details) == (precision == "bf16")
        if precision == "fp32":
            fp32_print = policy.info.fingerprint
    assert policy.info.fingerprint != fp32_print
    assert not np.array_equal(chunks["fp32"], chunks["bf16"])  # autocast did run
    scale = np.abs(chunks["fp32"]).max()
    assert np.abs(chunks["fp32"] - chunks["bf16"]).max() < 0.05 * scale
    with pytest.raises(ValueError, match=r"precision='fp16' is invalid.*fp32.*bf16"):
        LeRobotPolicy(tiny_ckpt, precision="fp16")


def test_import_so101_sim_harness_loads_no_torch():
    import subprocess

    code = ("import sys, so101_sim, so101_sim.harness, so101_sim.testing; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"
    assert expert_policy().info.needs_env_state

"""The eval command's start-up: the collector paused and frozen in a process so101-sim owns,
and the env workers' fork server and the render self-check started while the checkpoint
loads; the record command's workers' fork server started while the dataset opens, and the
curve command's before its first checkpoint loads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

COLLECTOR = textwrap.dedent("""
    import gc, json, sys, weakref
    from so101_sim.utils.collector import freeze_for_exit, own_process, startup_objects

    class Node:
        pass

    def cycle():  # garbage only the cyclic collector can free
        a, b = Node(), Node()
        a.b, b.a = b, a
        return weakref.ref(a)

    out = {"frozen_before": gc.get_freeze_count()}
    if sys.argv[1] == "owned":
        own_process()
    with startup_objects():
        out["enabled_inside"] = gc.isenabled()
        dead = cycle()
        keep = [Node() for _ in range(1000)]
    out["cycle_collected"] = dead() is None
    out["enabled_after"] = gc.isenabled()
    out["frozen"] = gc.get_freeze_count()
    freeze_for_exit()
    out["frozen_at_exit"] = gc.get_freeze_count()
    print(json.dumps(out))
""")


def _run(code: str, *args: str, env: dict | None = None) -> dict:
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                         timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_an_owned_process_freezes_what_start_up_made_and_still_collects_its_garbage():
    owned = _run(COLLECTOR, "owned")
    assert owned["enabled_inside"] is False  # paused while the block imports and loads
    assert owned["enabled_after"] is True
    assert owned["cycle_collected"] is True  # the one collection at the end frees garbage
    assert owned["frozen"] > owned["frozen_before"] + 1000  # the survivors, Nodes and all
    assert owned["frozen_at_exit"] >= owned["frozen"]


def test_a_library_caller_keeps_its_collector_untouched():
    plain = _run(COLLECTOR, "library")
    assert plain["enabled_inside"] is True
    assert plain["frozen"] == plain["frozen_at_exit"] == plain["frozen_before"]


WARM = textwrap.dedent("""
    import json, os, sys
    sys.path.insert(0, sys.argv[1])
    from so101_sim.harness.warmup import warm_eval_workers
    from so101_sim.workers import start_pool
    from probe_service import ProbeFactory

    assert "MUJOCO_GL" not in os.environ
    warmed = warm_eval_workers(videos=False)
    with start_pool(ProbeFactory(), 1, name="test-probe") as pool:  # no preload of its own
        pool.submit(0, "probe")
        (reply,) = pool.collect()
    print(json.dumps({"warmed": warmed, "parent_gl": os.environ.get("MUJOCO_GL"),
                      "worker": reply.value}))
""")

PROBE = textwrap.dedent("""
    import os, sys

    class Probe:
        def probe(self):
            return {"gl": os.environ.get("MUJOCO_GL"),
                    "modules": [m for m in ("so101_sim.sim.env", "so101_sim.utils.image_pipeline",
                                            "torch") if m in sys.modules]}

    class ProbeFactory:
        def __call__(self):
            return Probe()
""")


def test_the_fork_server_started_early_passes_its_gl_choice_and_imports_to_workers(tmp_path):
    (tmp_path / "probe_service.py").write_text(PROBE)
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = _run(WARM, str(tmp_path), env=env)
    assert out["warmed"] is True
    assert out["parent_gl"] in ("egl", "osmesa")
    # The worker sees the backend chosen before the server started, and the server's imports.
    assert out["worker"]["gl"] == out["parent_gl"]
    assert out["worker"]["modules"] == ["so101_sim.sim.env", "so101_sim.utils.image_pipeline",
                                        "torch"]


EARLY = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import so101_sim.harness.frames as frames
    from so101_sim.harness.frames import choose_rendering
    from so101_sim.harness.policies import PolicyInfo
    from so101_sim.harness.warmup import EarlySelfCheck, start_self_check, warm_eval_workers
    from so101_sim.tasks import load_task

    ckpt, mode = Path(sys.argv[1]), sys.argv[2]
    info = PolicyInfo(name="p", cameras=("front", "side"), image_size=(60, 80),
                      train_image_size=(480, 640), n_obs_steps=2, n_action_steps=8)
    out = {}
    if mode == "early":
        out["warmed"] = warm_eval_workers(videos=False)
        out["started"] = start_self_check(ckpt, "pick_place")
        out["other_task"] = start_self_check(ckpt, "lift")  # asked below for pick_place only
        out["faithful_only"] = start_self_check(ckpt / "missing", "pick_place")
        broken = EarlySelfCheck(load_task("pick_place"), ("nowhere",), (480, 640), (60, 80))
        out["broken"] = broken.result()
        here = frames._self_check
        def refuse(*args):
            raise AssertionError("the early answer should have been used")
        frames._self_check = refuse  # only this process: the early check runs in another
    rendering = choose_rendering(info, None, task=load_task("pick_place"), faithful=False,
                                 log=lambda line: None)
    out.update(size=list(rendering.render_size), label=rendering.label, check=rendering.check,
               pending=len(frames._AHEAD))
    print(json.dumps(out))
""")


def test_the_self_check_started_early_gives_the_answer_of_one_run_here():
    """`eval` starts the render self-check in a worker process while the policy loads; the
    answer is the one choose_rendering finds itself, and a check asked for other inputs, or
    one that fails, leaves choose_rendering to check here."""
    ckpt = str(Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion")
    here, early = _run(EARLY, ckpt, "here"), _run(EARLY, ckpt, "early")
    assert early["warmed"] and early["started"] and early["other_task"]
    assert early["faithful_only"] is False and early["broken"] is None
    assert here["size"] == early["size"] == [180, 240]
    assert early["label"] == here["label"] and early["check"] == here["check"]
    assert early["pending"] == 1 and here["pending"] == 0  # lift's was never asked for


AGAINST = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import so101_sim.harness.frames as frames
    from so101_sim.cli import main

    ckpt, ref, out = sys.argv[1:4]
    def refuse(*args):
        raise AssertionError("the early answer should have been used")
    frames._self_check = refuse  # this process only: the fork server imports its own copy
    rc = main(["eval", "--policy", ckpt, "--against", ref, "--max-episodes", "1",
               "--n-envs", "1", "--videos", "0", "--out", out])
    info = json.loads((Path(out) / "eval_info.json").read_text())
    print(json.dumps({"rc": rc, "check": info["config"].get("image_check"),
                      "images": info["config"]["images"],
                      "episodes": info["sequential_verdict"]["episodes"]}))
""")


def test_an_against_run_uses_the_self_check_started_early(tmp_path):
    """`eval --against RUN` takes its task from RUN before the policy loads, so its render
    self-check starts early too, as a plain eval's does."""
    from so101_sim.tasks import load_task

    ckpt = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"
    ref = tmp_path / "ref"
    ref.mkdir()
    info = {"per_episode": [{"seed": s, "success": True, "actions_sha": None}
                            for s in (100_000, 100_001)],
            "config": {"policy": "ref", "policy_fingerprint": "ref", "task": "pick_place",
                       "task_sha256": load_task("pick_place").sha256(),
                       "images": "reduced: rendered at 180x240"}}
    (ref / "eval_info.json").write_text(json.dumps(info))
    out = _run(AGAINST, str(ckpt), str(ref), str(tmp_path / "out"))
    assert out["rc"] == 0 and out["episodes"] == 1
    # the self-check's numbers came from the early process (here it would have raised)
    assert out["check"] is not None and out["images"].startswith("reduced: rendered at")


# Where the command starts its heavy import here (opening a dataset imports lerobot; curve's
# first evaluation loads torch and the checkpoint), the fork server must be running with the
# workers' preload: say so, and stop (the server too: it would import on for seconds, holding
# the pipe subprocess.run reads).
STOP_HERE = """
    import json, os, signal, sys
    from multiprocessing import forkserver

    def stop_here(*args, **kwargs):
        pid = forkserver._forkserver._forkserver_pid
        print(json.dumps({"server_pid": pid,
                          "preload": list(forkserver._forkserver._preload_modules)}))
        if pid is not None:
            os.kill(pid, signal.SIGKILL)
        sys.stdout.flush()
        os._exit(0)
"""

RECORD = textwrap.dedent(STOP_HERE + """
    import so101_sim.dataset.writer as writer
    from so101_sim.record import record

    writer.open_dataset = stop_here
    record(sys.argv[1], 1, image_size=(48, 64), progress=False)
""")


@pytest.mark.usefixtures("child_tmpdir")
def test_record_starts_its_workers_fork_server_before_it_opens_the_dataset(tmp_path):
    """`record` starts the workers' fork server, importing what they need, before the dataset
    (and lerobot with it) opens here."""
    from so101_sim.record.loop import WORKER_PRELOAD

    out = _run(RECORD, str(tmp_path / "ds"))
    assert out["server_pid"] is not None
    assert out["preload"][:len(WORKER_PRELOAD)] == list(WORKER_PRELOAD)


EXPERT_ROLLOUTS = textwrap.dedent(STOP_HERE + """
    import so101_sim.harness.rollouts as rollouts
    from so101_sim.cli import main

    rollouts.rollout_sink = stop_here
    main(["eval", "--policy", "expert", "--episodes", "1", "--n-envs", "1", "--image-size",
          "48x64", "--videos", "0", "--out", sys.argv[1], "--save-rollouts", sys.argv[2]])
""")


@pytest.mark.usefixtures("child_tmpdir")
def test_an_expert_eval_that_saves_rollouts_starts_the_fork_server_before_the_dataset(
        tmp_path):
    """Without a checkpoint to load, `eval --save-rollouts` still imports lerobot here for
    the rollout dataset: the workers' fork server (which imports it too) starts first."""
    from so101_sim.harness.warmup import worker_preload

    out = _run(EXPERT_ROLLOUTS, str(tmp_path / "eval"), str(tmp_path / "rollouts"))
    assert out["server_pid"] is not None
    want = worker_preload(resize=True, rollouts=True, videos=False)
    assert out["preload"][:len(want)] == list(want)


CURVE = textwrap.dedent(STOP_HERE + """
    import so101_sim.harness.runner as runner
    from so101_sim.cli import main

    runner.evaluate = stop_here  # where the first checkpoint's evaluation would load it
    main(["curve", sys.argv[1], "--episodes", "1", "--n-envs", "1"])
""")


@pytest.mark.usefixtures("child_tmpdir")
def test_curve_starts_the_workers_fork_server_before_its_first_checkpoint_loads(tmp_path):
    """`so101-sim curve` imports torch and loads each checkpoint here: the workers' fork
    server is already importing what they need on the other core when the first one does."""
    from tiny_policy import make_tiny_diffusion_checkpoint

    from so101_sim.harness.warmup import worker_preload

    run = tmp_path / "run"
    make_tiny_diffusion_checkpoint(run / "checkpoints" / "step_0000100" / "pretrained_model")
    out = _run(CURVE, str(run))
    assert out["server_pid"] is not None
    want = worker_preload(resize=True, rollouts=False, videos=False)
    assert out["preload"][:len(want)] == list(want)

"""Record scripted-expert demonstrations as a LeRobotDataset v3, and replay them.

Everything is written through lerobot's own API (``LeRobotDataset.create`` / ``resume``,
``add_frame``, ``save_episode``, ``finalize``) so the result loads in lerobot unchanged. Each
frame also carries the episode's reset seed and initial cube pose, so any episode can be
re-simulated exactly (``replay``). A small JSON sidecar in the dataset folder remembers every
seed tried (kept or discarded), the noise level, the expert options and the codec, so
``resume`` never repeats a seed and never mixes settings.

Workers (``--workers N``, local processes or Ray actors through ``so101_sim.workers``)
simulate, render and encode whole episodes (``record_worker``); this process is the only
writer and stores episodes in seed order (``record_loop``), so the dataset is the same
whatever the number of workers or the backend. Every finished episode is spooled before it is
written and the dataset is checkpointed every ``checkpoint_every`` episodes
(``record_store``): Ctrl-C or SIGTERM ends with a finalized dataset, and after a hard kill
(SIGKILL, OOM, power loss) ``resume`` ends with every finished episode, no manual step.

DART noise (``dart_noise > 0``): the env executes the expert's action plus Gaussian noise drawn
from a per-episode stream seeded by the episode seed; ``action`` stays the expert's clean
action (the label) and ``action_executed`` stores what was executed, which ``replay`` uses.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.record_store import SIDECAR, read_sidecar
from so101_sim.units import FEATURE_NAMES
from so101_sim.workers import check_backend

#: Demonstrations come from the training seed range; seeds >= this are for evaluation only.
EVAL_SEED_START = 100_000
DEFAULT_REPO_ID = "local/so101_pick_place"
ROBOT_TYPE = "so101_follower"
CAMERAS = ("front", "side")
VIDEO_KEYS = tuple(f"observation.images.{cam}" for cam in CAMERAS)
#: Video codecs `record` offers. h264 (libx264 "veryfast", crf 23) costs about half the CPU of
#: lerobot's default AV1 (libsvtav1 preset 12, crf 30) per 480x640 frame at a similar file size
#: and PSNR, and decodes ~3x faster; that is what lets two cores record >= 50 env-steps/s.
VCODECS: dict[str, dict[str, Any]] = {
    "h264": {"vcodec": "h264", "preset": "veryfast", "crf": 23},
    "libsvtav1": {"vcodec": "libsvtav1"},
}
DEFAULT_VCODEC = "h264"
_DART_STREAM = 0xDA27  # second SeedSequence word: the noise never correlates with the jitter


def dataset_features(image_size: tuple[int, int],
                     dart: bool = False) -> dict[str, dict[str, Any]]:
    """lerobot feature spec: state/action, two video cameras, and the re-simulation extras."""
    h, w = image_size
    names = list(FEATURE_NAMES)
    feats: dict[str, dict[str, Any]] = {
        "observation.state": {"dtype": "float32", "shape": (6,), "names": names},
        "action": {"dtype": "float32", "shape": (6,), "names": names},
    }
    for key in VIDEO_KEYS:
        feats[key] = {"dtype": "video", "shape": (h, w, 3),
                      "names": ["height", "width", "channels"]}
    feats["episode_seed"] = {"dtype": "int64", "shape": (1,), "names": None}
    feats["initial_cube_pose"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "yaw_deg"]}
    if dart:
        feats["action_executed"] = {"dtype": "float32", "shape": (6,), "names": names}
    return feats


def check_seed_range(seed_start: int, n_seeds: int = 1) -> None:
    """Refuse evaluation seeds: demos trained on them would leak into the benchmark."""
    if seed_start < 0:
        raise ValueError(f"seed_start={seed_start} is negative; demo seeds are "
                         f"0..{EVAL_SEED_START - 1}")
    if seed_start + n_seeds > EVAL_SEED_START:
        raise ValueError(
            f"seeds {seed_start}..{seed_start + n_seeds - 1} reach the evaluation range "
            f"(>= {EVAL_SEED_START}); demonstrations must use training seeds "
            f"0..{EVAL_SEED_START - 1}")


def check_dart_noise(dart_noise: float) -> float:
    """The noise std as a float, or a ValueError that says what to pass instead."""
    try:
        x = float(dart_noise)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x) or x < 0:
        raise ValueError(f"dart_noise={dart_noise!r} is invalid; expected a finite number >= 0 "
                         "(std of the executed-action noise: degrees for the arm joints, "
                         "0..100 units for the gripper); pass e.g. --dart-noise 2, or 0 for none")
    return x


def expert_options(recover: bool = False, grasp_clearance: float | None = None
                   ) -> dict[str, Any]:
    """ScriptedExpert keyword options as stored in the sidecar (defaults left out)."""
    options: dict[str, Any] = {}
    if recover:
        options["recover"] = True
    if grasp_clearance is not None:
        c = float(grasp_clearance)
        if not (math.isfinite(c) and 0.0 <= c <= 0.02):
            raise ValueError(f"grasp_clearance={grasp_clearance!r} is invalid; expected metres "
                             "in [0, 0.02] (the open gripper leaves ~0.025 m around the cube); "
                             "e.g. --grasp-clearance 0.012")
        options["clearance"] = c
    return options


def _check_args(n_episodes: int, workers: int, seed_start: int, vcodec: str | None,
                checkpoint_every: int) -> None:
    if n_episodes < 1:
        raise ValueError(f"n_episodes={n_episodes}; expected >= 1")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers={workers!r} is invalid; expected an integer >= 1, e.g. "
                         f"--workers {os.cpu_count() or 2} (one per CPU core)")
    if vcodec is not None and vcodec not in VCODECS:
        raise ValueError(f"vcodec={vcodec!r} is not supported; expected one of "
                         f"{sorted(VCODECS)} (--vcodec h264 is the fast default)")
    if not isinstance(checkpoint_every, int) or checkpoint_every < 1:
        raise ValueError(f"checkpoint_every={checkpoint_every!r} is invalid; expected an "
                         "integer >= 1 (episodes between dataset checkpoints), e.g. "
                         "--checkpoint-every 50")
    check_seed_range(seed_start)


# ----------------------------------------------------------------------------- seeds
def _read_frames(root: Path, columns: list[str]) -> Any:
    """All rows of the dataset's data parquet files (only `columns`), as a pandas DataFrame."""
    import pandas as pd
    import pyarrow.parquet as pq

    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        return pd.DataFrame(columns=columns)
    return pd.concat([pq.read_table(f, columns=columns).to_pandas() for f in files],
                     ignore_index=True)


def _features(root: Path) -> dict[str, Any]:
    path = root / "meta" / "info.json"
    return json.loads(path.read_text()).get("features", {}) if path.exists() else {}


def stored_seeds(root: str | Path) -> list[int]:
    """Seed of every episode stored in a finalized dataset, in episode order."""
    df = _read_frames(Path(root), ["episode_index", "episode_seed"])
    if len(df) == 0:
        return []
    first = df.groupby("episode_index")["episode_seed"].first()
    return [int(np.asarray(v).reshape(-1)[0]) for v in first.sort_index()]


# ----------------------------------------------------------------------------- one episode
def _dart_rng(seed: int) -> np.random.Generator:
    """Noise stream of one episode: fixed by its seed, independent of the expert's jitter."""
    return np.random.default_rng([seed, _DART_STREAM])


def run_episode(env: Any, expert: Any, seed: int, emit: Callable[[dict[str, Any]], None],
                dart_noise: float = 0.0) -> tuple[bool, str | None, int]:
    """Roll the expert for one episode, passing every frame (lerobot's frame dict) to `emit`.

    With `dart_noise`, the env executes ``clip(action + N(0, dart_noise))`` while the frame's
    ``action`` stays the clean expert action; ``action_executed`` holds what was executed.
    The expert follows absolute joint targets, so each clean label also points back from the
    perturbed state to the plan (the DART idea). Returns (success, failure_mode, steps).
    """
    obs, info = env.reset(seed=seed)
    expert.reset(seed)
    rng = _dart_rng(seed) if dart_noise > 0 else None
    cube = np.asarray(info["cube_pose"], dtype=np.float32)
    seed_arr = np.array([seed], dtype=np.int64)
    description = env.task.description
    steps, done, step_info = 0, False, {}
    while not done:
        action = np.asarray(expert.select_action(obs), dtype=np.float32)
        executed = action
        frame = {"observation.state": obs["agent_pos"].astype(np.float32), "action": action,
                 "episode_seed": seed_arr, "initial_cube_pose": cube, "task": description}
        if rng is not None:
            noisy = action + rng.normal(0.0, dart_noise, size=action.shape)
            executed = np.clip(noisy, env.action_low, env.action_high).astype(np.float32)
            frame["action_executed"] = executed
        for key, cam in zip(VIDEO_KEYS, CAMERAS, strict=True):
            if "pixels" in obs:  # a state-only env gives none (success-rate studies)
                frame[key] = obs["pixels"][cam]
        emit(frame)
        obs, _, terminated, truncated, step_info = env.step(executed)
        steps += 1
        done = terminated or truncated
    return bool(step_info.get("is_success", False)), step_info.get("failure_mode"), steps


def _task_arg(task: str | Path, root: Path, resume: bool) -> str:
    """The task as stored in the sidecar: a name, or an absolute .toml path."""
    if resume and (root / SIDECAR).exists():
        return str(read_sidecar(root).get("task", task))
    return str(Path(task).resolve()) if Path(str(task)).suffix == ".toml" else str(task)


# ----------------------------------------------------------------------------- record
def quiet_libav() -> None:
    """Hide libav's info chatter (x264's per-file statistics, remux notes) on the console."""
    import av

    av.logging.set_libav_level(av.logging.WARNING)


def record(out_dir: str | Path, n_episodes: int, task: str | Path = "pick_place",
           seed_start: int = 0, image_size: tuple[int, int] = (480, 640),
           keep_failures: bool = False, resume: bool = False, workers: int = 1,
           repo_id: str = DEFAULT_REPO_ID, progress: bool = True, dart_noise: float = 0.0,
           vcodec: str | None = None, recover: bool = False,
           grasp_clearance: float | None = None, backend: str = "local",
           ray_address: str | None = None, checkpoint_every: int = 50) -> dict[str, Any]:
    """Record `n_episodes` expert episodes (only successes unless `keep_failures`) to `out_dir`.

    Seeds run upward from `seed_start` (or, with `resume`, from after the largest seed already
    tried); episodes are stored in seed order whatever `workers` and `backend` are. `workers`
    processes (``backend="local"``) or Ray actors (``"ray"``: a local Ray runtime, or the
    cluster at `ray_address`, ``"auto"`` or ``host:port``) simulate, render and encode.
    Every finished episode is spooled, and the dataset is checkpointed every
    `checkpoint_every` episodes and on any exit we can catch (Ctrl-C, SIGTERM); after a hard
    kill, `resume` recovers every finished episode (see ``record_store``). `vcodec` is
    ``"h264"`` (default for new datasets) or ``"libsvtav1"``; a resumed dataset keeps its own.
    `dart_noise` is the std of the noise added to executed actions (``run_episode``), 0 for
    none; `recover` and `grasp_clearance` are ScriptedExpert options (retries; gap between
    the fixed pad and the cube at the grasp, metres), stored with the dataset. Returns a
    summary dict (episodes, successes, tried, env_steps, steps_per_s, seconds, and the
    time_physics / time_render / cpu_seconds spent by all recording processes).
    """
    from so101_sim.record_dataset import open_dataset
    from so101_sim.record_loop import Tally, record_episodes
    from so101_sim.record_store import SCRATCH
    from so101_sim.record_worker import RecorderSpec
    from so101_sim.task import load_task

    _check_args(n_episodes, workers, seed_start, vcodec, checkpoint_every)
    check_backend(backend, ray_address)
    if backend == "ray":  # say so before a dataset folder is created
        from so101_sim.workers.ray_pool import import_ray

        import_ray()
    dart_noise = check_dart_noise(dart_noise)
    expert = expert_options(recover, grasp_clearance)
    quiet_libav()
    from so101_sim.rendering import select_gl_backend

    select_gl_backend()  # choose (and print) once here: workers inherit MUJOCO_GL
    root = Path(out_dir)
    image_size = (int(image_size[0]), int(image_size[1]))
    task_arg = _task_arg(task, root, resume)
    spec = load_task(task_arg)
    if spec.fps != 30:
        raise ValueError(f"task fps is {spec.fps}; the dataset is recorded at 30 fps")
    cpu0 = time.process_time()
    opened = open_dataset(root, resume, repo_id, task_arg, image_size, seed_start, dart_noise,
                          vcodec, spec.max_steps + 2, expert)
    side = opened.side
    tally = Tally(root, side, opened.ds.meta.total_episodes, n_episodes, progress)
    worker_spec = RecorderSpec(side["task"], image_size, side["dart_noise"], side["expert"],
                               keep_failures, opened.encoder_kwargs, spec.max_steps + 2,
                               str((root / SCRATCH).resolve()))
    record_episodes(opened, tally, worker_spec, workers, backend, ray_address,
                    checkpoint_every, spec.description)
    tally.cpu_seconds += time.process_time() - cpu0
    return tally.summary(workers, backend)


# ----------------------------------------------------------------------------- replay
def replay(dataset_dir: str | Path, episode: int) -> float:
    """Re-simulate episode `episode` from its stored seed and actions (state-only env).

    Uses ``action_executed`` where the dataset has it (DART noise), else ``action``. Returns
    the largest absolute difference between the recorded ``observation.state`` and the
    re-simulated ``agent_pos`` over the episode; 0 because the simulation is deterministic.
    """
    from so101_sim.env import PickPlaceEnv

    root = Path(dataset_dir)
    act_key = "action_executed" if "action_executed" in _features(root) else "action"
    df = _read_frames(root, ["episode_index", "frame_index", "episode_seed",
                             "observation.state", act_key])
    ep = df[df["episode_index"] == episode].sort_values("frame_index")
    if len(ep) == 0:
        n = df["episode_index"].nunique()
        raise ValueError(f"episode {episode} not in {root} (it has {n} episodes, 0..{n - 1})")
    seed = int(np.asarray(ep["episode_seed"].iloc[0]).reshape(-1)[0])
    states = np.stack([np.asarray(s, dtype=np.float32) for s in ep["observation.state"]])
    actions = np.stack([np.asarray(a, dtype=np.float32) for a in ep[act_key]])
    task = read_sidecar(root).get("task", "pick_place")

    env = PickPlaceEnv(task=task, obs_type="state")
    try:
        obs, _ = env.reset(seed=seed)
        worst = 0.0
        for state, action in zip(states, actions, strict=True):
            worst = max(worst, float(np.max(np.abs(obs["agent_pos"] - state))))
            obs, *_ = env.step(action)
    finally:
        env.close()
    return worst

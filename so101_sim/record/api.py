"""Record scripted-expert demonstrations as a LeRobotDataset v3, and replay them.

Everything is written through lerobot's own API (``LeRobotDataset.create`` / ``resume``,
``add_frame``, ``save_episode``, ``finalize``) so the result loads in lerobot unchanged. Each
frame also carries the episode's reset seed and initial cube pose, so any episode can be
re-simulated exactly (``replay``). A small JSON sidecar in the dataset folder remembers every
seed tried (kept or discarded), the noise level, the expert options and the codec, so
``resume`` never repeats a seed and never mixes settings.

Workers (``--workers N``, local processes or Ray actors through ``so101_sim.workers``)
simulate, render and encode whole episodes (``record.worker``); this process is the only
writer and stores episodes in seed order (``record.loop``), so the dataset is the same
whatever the number of workers or the backend. Every finished episode is spooled before it is
written and the dataset is checkpointed every ``checkpoint_every`` episodes
(``dataset.store``): Ctrl-C or SIGTERM ends with a finalized dataset, and after a hard kill
(SIGKILL, OOM, power loss) ``resume`` ends with every finished episode, no manual step.

DART noise: see ``record.episode``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path
from shlex import quote
from typing import Any

import numpy as np

from so101_sim.dataset.reader import info_features, read_frames
from so101_sim.dataset.robot_episodes import ROBOT_EPISODES, read_robot_episodes
from so101_sim.dataset.schema import (
    DEFAULT_REPO_ID,
    EVAL_SEED_START,
    VCODECS,
    check_seed_range,
    check_video_size,
)
from so101_sim.dataset.store import SCRATCH, SIDECAR, read_sidecar
from so101_sim.record.episode import check_dart_noise, expert_options
from so101_sim.sim import IMAGE_SIZE, SO101Env
from so101_sim.sim.env_args import check_cameras
from so101_sim.sim.rendering import select_gl_backend
from so101_sim.tasks import DEFAULT_TASK, load_task
from so101_sim.utils.devices import RECORD_WORKER_MB, cpu_count, workers_that_fit
from so101_sim.utils.locks import folder_lock
from so101_sim.utils.numbers import check_count
from so101_sim.utils.text import counted
from so101_sim.utils.versions import installed
from so101_sim.utils.video_backend import quiet_libav
from so101_sim.workers import check_backend
from so101_sim.workers.local import start_fork_server


def _check_args(n_episodes: int, workers: int, seed_start: int, vcodec: str | None,
                checkpoint_every: int, resuming: bool) -> None:
    check_count("n_episodes", n_episodes, 1, "episodes to record")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers={workers!r} is invalid; expected an integer >= 1, e.g. "
                         f"--workers {cpu_count()} (one per CPU core)")
    if vcodec is not None and vcodec not in VCODECS:
        raise ValueError(f"vcodec={vcodec!r} is not supported; expected one of "
                         f"{sorted(VCODECS)} (--vcodec h264 is the fast default)")
    if not isinstance(checkpoint_every, int) or checkpoint_every < 1:
        raise ValueError(f"checkpoint_every={checkpoint_every!r} is invalid; expected an "
                         "integer >= 1 (episodes between dataset checkpoints), e.g. "
                         "--checkpoint-every 50")
    # a new dataset needs at least one seed per episode (more if the expert fails some)
    check_seed_range(seed_start, 1 if resuming else n_episodes)


def _task_arg(task: str | Path | None, stored: dict[str, Any], root: Path) -> str:
    """The task as the sidecar stores it (a name, or an absolute .toml path): a resumed
    dataset's own, refusing another one by name."""
    if stored:
        own = str(stored.get("task", DEFAULT_TASK))
        if task is not None and load_task(task).name != load_task(own).name:
            raise ValueError(f"{root} holds {load_task(own).name} demos, not "
                             f"{load_task(task).name}; resume without --task, or record "
                             "another task into another --out (a dataset holds one task)")
        return own
    task = DEFAULT_TASK if task is None else task
    return str(Path(task).resolve()) if Path(str(task)).suffix == ".toml" else str(task)


# ----------------------------------------------------------------------------- record


def record(out_dir: str | Path, n_episodes: int, task: str | Path | None = None,
           seed_start: int = 0, image_size: tuple[int, int] | None = None,
           cameras: Sequence[str] | None = None, keep_failures: bool = False,
           resume: bool = False, workers: int = 1,
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
    kill, `resume` recovers every finished episode (see ``dataset.store``). `cameras` are the
    cameras recorded (default the task's; ``("front", "side", "wrist")`` adds the wrist); a
    resumed dataset keeps its own, as it keeps its `task` (default pick_place) and
    `image_size` (default 480x640) when they are None. `vcodec` is
    ``"h264"`` (default for new datasets) or ``"libsvtav1"``; a resumed dataset keeps its own.
    `dart_noise` is the std of the noise added to executed actions (``run_episode``), 0 for
    none; `recover` and `grasp_clearance` are ScriptedExpert options (retries; gap between
    the fixed pad and the cube at the grasp, metres), stored with the dataset. Returns a
    summary dict (episodes, successes, tried, env_steps, steps_per_s, seconds, and the
    time_physics / time_render / cpu_seconds spent by all recording processes).
    """
    from so101_sim.dataset.writer import open_dataset
    from so101_sim.record.loop import WORKER_PRELOAD, Tally, record_episodes
    from so101_sim.record.worker import RecorderSpec

    _check_args(n_episodes, workers, seed_start, vcodec, checkpoint_every,
                resume and (Path(out_dir) / SIDECAR).exists())
    check_backend(backend, ray_address)
    if image_size is not None:  # a resumed dataset's own size was checked when it was made
        check_video_size(tuple(image_size), "--image-size")
    if backend == "ray":  # say so before a dataset folder is created
        from so101_sim.workers.ray_pool import import_ray

        import_ray()
    dart_noise = check_dart_noise(dart_noise)
    expert = expert_options(recover, grasp_clearance)
    quiet_libav()
    select_gl_backend()  # choose (and print) once here: workers inherit MUJOCO_GL
    if backend == "local":  # an out-of-memory kill would take every worker with it
        workers = workers_that_fit(workers, mb_each=RECORD_WORKER_MB, command="record",
                                   unit="workers", same="the dataset is the same for any "
                                   "--workers")
    root = Path(out_dir)
    with folder_lock(root, "the dataset"):  # one writer; taken before anything is written
        stored = read_sidecar(root) if resume and (root / SIDECAR).exists() else {}
        task_arg = _task_arg(task, stored, root)
        if image_size is None:
            image_size = stored.get("image_size") or IMAGE_SIZE
        image_size = (int(image_size[0]), int(image_size[1]))
        spec = load_task(task_arg)
        if spec.fps != 30:
            raise ValueError(f"--task {task_arg}: its fps is {spec.fps}; expected 30, the only "
                             "rate so101-sim record writes (the SO-101 datasets' rate): set "
                             "fps = 30 in the task file")
        cams = check_cameras(spec.cameras if cameras is None else cameras)
        if backend == "local":  # the workers' fork server imports torch on the other core
            # while open_dataset imports lerobot here (they took turns: ~6 s each)
            start_fork_server(WORKER_PRELOAD)
        cpu0 = time.process_time()
        opened = open_dataset(root, resume, repo_id, task_arg, image_size, seed_start,
                              dart_noise, vcodec, spec.max_steps + 2, expert, cams,
                              cameras_given=cameras is not None)
        spec = dataclasses.replace(spec, cameras=tuple(opened.side["cameras"]))
        side = opened.side
        have = opened.ds.meta.total_episodes
        if resume and have < n_episodes and opened.next_seed + n_episodes - have > EVAL_SEED_START:
            opened.checkpoint(reopen=False)  # close it as it was: nothing was recorded
            raise ValueError(
                f"{root} has {have} episodes and its next seed is {opened.next_seed}: "
                f"{n_episodes - have} more would reach the evaluation seeds (>= "
                f"{EVAL_SEED_START}); at most {have + EVAL_SEED_START - opened.next_seed} "
                "episodes fit, so ask for fewer, or record the rest into another --out with a "
                "lower --seed-start")
        tally = Tally(root, side, have, n_episodes, progress)
        worker_spec = RecorderSpec(spec, image_size, side["dart_noise"], side["expert"],
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
    A dataset lerobot-record wrote through ``--robot.type=so101_sim`` gives the seed, task and
    sim steps in the robot's notes (``dataset.robot_episodes``); its frames after the sim
    episode ended held the last state, and are compared with it.
    """
    root = Path(dataset_dir)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset (no meta/info.json); expected "
                                "the --out folder of `so101-sim record`")
    features = info_features(root)
    note = None if "episode_seed" in features else read_robot_episodes(root).get(episode)
    if "episode_seed" not in features and note is None:
        robot = json.loads((root / "meta" / "info.json").read_text()).get("robot_type")
        hint = (f"; it was recorded through --robot.type={robot} before the robot noted its "
                f"seeds (no episode {episode} in {ROBOT_EPISODES}), so replay it with "
                f"lerobot-replay --robot.type={robot} --robot.seed=SEED "
                f"--robot.episode_end=hold {quote(f'--dataset.repo_id=local/{root.name}')} "
                f"{quote(f'--dataset.root={root}')} --dataset.episode={episode} (SEED: that "
                "episode's seed in lerobot-record's --robot.outcomes_path "
                "file)") if robot == "so101_sim" else ""
        raise ValueError(f"{root} has no episode_seed feature: replay re-simulates an episode "
                         "from the reset seed `so101-sim record` stores, so it needs a dataset "
                         f"recorded by so101-sim{hint}")
    act_key = "action_executed" if "action_executed" in features else "action"
    df = read_frames(root, ["episode_index", "frame_index", "observation.state", act_key,
                            *([] if note else ["episode_seed"])])
    ep = df[df["episode_index"] == episode].sort_values("frame_index")
    if len(ep) == 0:
        n = df["episode_index"].nunique()
        raise ValueError(f"episode {episode} not in {root} (it has {counted(n, 'episode')}, "
                         f"0..{n - 1})")
    states = np.stack([np.asarray(s, dtype=np.float32) for s in ep["observation.state"]])
    actions = np.stack([np.asarray(a, dtype=np.float32) for a in ep[act_key]])
    if note is None:
        seed = int(np.asarray(ep["episode_seed"].iloc[0]).reshape(-1)[0])
        task, steps = read_sidecar(root).get("task", DEFAULT_TASK), len(states)
    else:
        seed, task = note["seed"], note["task"]
        steps = note["steps"] if type(note.get("steps")) is int else len(states)

    env = SO101Env(task=task, obs_type="state")
    try:
        obs, _ = env.reset(seed=seed)
        worst = 0.0
        for k, (state, action) in enumerate(zip(states, actions, strict=True)):
            worst = max(worst, float(np.max(np.abs(obs["agent_pos"] - state))))
            if k < steps:  # later frames: the robot held the ended episode's last state
                obs, *_ = env.step(action)
    finally:
        env.close()
    return worst


def replay_versions(dataset_dir: str | Path) -> str:
    """"" when this MuJoCo is the one that recorded the dataset, else what each was (physics
    may differ between releases, so a nonzero deviation may be theirs, not the dataset's)."""
    recorded, now = read_sidecar(Path(dataset_dir)).get("mujoco"), installed("mujoco")
    if not recorded or recorded == now:
        return ""
    return f" (recorded with MuJoCo {recorded}, re-simulated with {now})"

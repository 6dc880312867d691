"""Record scripted-expert demonstrations as a LeRobotDataset v3, and replay them.

Everything is written through lerobot's own API (``LeRobotDataset.create`` / ``resume``,
``add_frame``, ``save_episode``, ``finalize``) so the result loads in lerobot unchanged. Each
frame also carries the episode's reset seed and initial cube pose, so any episode can be
re-simulated exactly (``replay``). A small JSON sidecar in the dataset folder remembers every
seed tried (kept or discarded), so ``resume`` never repeats one.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.units import FEATURE_NAMES

#: Demonstrations come from the training seed range; seeds >= this are for evaluation only.
EVAL_SEED_START = 100_000
DEFAULT_REPO_ID = "local/so101_pick_place"
SIDECAR = "so101_sim_recording.json"
ROBOT_TYPE = "so101_follower"
CAMERAS = ("front", "side")


def dataset_features(image_size: tuple[int, int]) -> dict[str, dict[str, Any]]:
    """lerobot feature spec: state/action, two video cameras, and the re-simulation extras."""
    h, w = image_size
    names = list(FEATURE_NAMES)
    feats: dict[str, dict[str, Any]] = {
        "observation.state": {"dtype": "float32", "shape": (6,), "names": names},
        "action": {"dtype": "float32", "shape": (6,), "names": names},
    }
    for cam in CAMERAS:
        feats[f"observation.images.{cam}"] = {
            "dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]}
    feats["episode_seed"] = {"dtype": "int64", "shape": (1,), "names": None}
    feats["initial_cube_pose"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "yaw_deg"]}
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


# ----------------------------------------------------------------------------- sidecar / seeds
def _read_sidecar(root: Path) -> dict[str, Any]:
    path = root / SIDECAR
    return json.loads(path.read_text()) if path.exists() else {}


def _write_sidecar(root: Path, data: dict[str, Any]) -> None:
    """Atomic write, so an interruption never leaves a half-written sidecar."""
    tmp = root / (SIDECAR + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(root / SIDECAR)


def _read_frames(root: Path, columns: list[str]) -> Any:
    """All rows of the dataset's data parquet files (only `columns`), as a pandas DataFrame."""
    import pandas as pd
    import pyarrow.parquet as pq

    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        return pd.DataFrame(columns=columns)
    return pd.concat([pq.read_table(f, columns=columns).to_pandas() for f in files],
                     ignore_index=True)


def stored_seeds(root: str | Path) -> list[int]:
    """Seed of every episode stored in a finalized dataset, in episode order."""
    df = _read_frames(Path(root), ["episode_index", "episode_seed"])
    if len(df) == 0:
        return []
    first = df.groupby("episode_index")["episode_seed"].first()
    return [int(np.asarray(v).reshape(-1)[0]) for v in first.sort_index()]


# ----------------------------------------------------------------------------- signals
class _Interrupts:
    """Turns SIGINT/SIGTERM into KeyboardInterrupt, deferred while an episode is being saved.

    Deferring means a kill never lands inside ``save_episode`` (half-written parquet/video).
    """

    def __init__(self) -> None:
        self.critical = False
        self.pending: int | None = None
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        if self.critical:
            self.pending = signum
        else:
            raise KeyboardInterrupt(f"signal {signum}")

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with suppress(ValueError):  # not the main thread: leave signals alone
                self._old[sig] = signal.signal(sig, self._handler)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    @contextmanager
    def deferred(self) -> Iterator[None]:
        self.critical = True
        try:
            yield
        finally:
            self.critical = False
        if self.pending is not None:
            raise KeyboardInterrupt(f"signal {self.pending}")


# ----------------------------------------------------------------------------- record
def record(out_dir: str | Path, n_episodes: int, task: str | Path = "pick_place",
           seed_start: int = 0, image_size: tuple[int, int] = (480, 640),
           keep_failures: bool = False, resume: bool = False, workers: int = 1,
           repo_id: str = DEFAULT_REPO_ID, progress: bool = True,
           streaming_encoding: bool = True) -> dict[str, Any]:
    """Record `n_episodes` expert episodes (only successes unless `keep_failures`) to `out_dir`.

    Seeds run upward from `seed_start` (or, with `resume`, from after the largest seed already
    tried). Each episode is saved as soon as it ends and the dataset is finalized on any exit,
    including Ctrl-C / SIGTERM, so an interrupted run loads with every completed episode.
    Returns a summary dict (episodes, successes, tried, env_steps, steps_per_s, seconds).
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from so101_sim.env import PickPlaceEnv
    from so101_sim.expert import ScriptedExpert

    if workers != 1:
        raise ValueError(f"workers={workers}: only --workers 1 is supported for now")
    if n_episodes < 1:
        raise ValueError(f"n_episodes={n_episodes}; expected >= 1")
    check_seed_range(seed_start)
    root = Path(out_dir)
    image_size = (int(image_size[0]), int(image_size[1]))
    task_arg = str(Path(task).resolve()) if Path(str(task)).suffix == ".toml" else str(task)
    exists = root.exists() and any(root.iterdir())

    if exists and not resume:
        raise ValueError(f"{root} already exists and is not empty; pass --resume to continue "
                         "recording into it, or choose another --out")
    if resume and exists:
        side = _read_sidecar(root)
        if not (root / "meta" / "info.json").exists():
            raise ValueError(f"{root} is not a LeRobot dataset (no meta/info.json); "
                             "cannot --resume")
        if side.get("image_size") and tuple(side["image_size"]) != image_size:
            raise ValueError(f"{root} was recorded at {side['image_size'][0]}x"
                             f"{side['image_size'][1]}; resume with --image-size to match")
        tried = [int(s) for s in side.get("tried", [])] + stored_seeds(root)
        repo_id = side.get("repo_id", repo_id)
        task_arg = side.get("task", task_arg)
        ds = LeRobotDataset.resume(repo_id, root=root, streaming_encoding=streaming_encoding)
        failures = dict(side.get("failures", {}))
        next_seed = max([seed_start - 1, *tried]) + 1
    else:
        if root.exists():
            root.rmdir()  # empty: lerobot insists on creating the folder itself
        ds = LeRobotDataset.create(repo_id=repo_id, fps=30, features=dataset_features(image_size),
                                   root=root, robot_type=ROBOT_TYPE, use_videos=True,
                                   streaming_encoding=streaming_encoding)
        tried, failures, next_seed = [], {}, seed_start

    side = {"repo_id": repo_id, "task": task_arg, "image_size": list(image_size),
            "tried": sorted(set(tried)), "failures": failures}
    _write_sidecar(root, side)

    env = PickPlaceEnv(task=task_arg, obs_type="pixels_agent_pos_env_state",
                       image_size=image_size)
    expert = ScriptedExpert(env.task)
    if env.task.fps != 30:
        raise ValueError(f"task fps is {env.task.fps}; the dataset is recorded at 30 fps")
    description = env.task.description
    kept = ds.meta.total_episodes
    start_kept, successes, env_steps, t0 = kept, 0, 0, time.perf_counter()

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_episodes, initial=kept, unit="ep", desc="record")

    interrupts = _Interrupts()
    interrupts.install()
    try:
        while kept < n_episodes:
            seed = next_seed
            check_seed_range(seed)
            next_seed += 1
            obs, info = env.reset(seed=seed)
            expert.reset(seed)
            cube = np.asarray(info["cube_pose"], dtype=np.float32)
            seed_arr = np.array([seed], dtype=np.int64)
            done, step_info = False, {}
            while not done:
                action = expert.select_action(obs)
                frame = {"observation.state": obs["agent_pos"].astype(np.float32),
                         "action": np.asarray(action, dtype=np.float32),
                         "episode_seed": seed_arr, "initial_cube_pose": cube,
                         "task": description}
                for cam in CAMERAS:
                    frame[f"observation.images.{cam}"] = obs["pixels"][cam]
                ds.add_frame(frame)
                obs, _, terminated, truncated, step_info = env.step(action)
                env_steps += 1
                done = terminated or truncated
            success = bool(step_info.get("is_success", False))
            with interrupts.deferred():
                if success or keep_failures:
                    ds.save_episode()
                    kept += 1
                else:
                    ds.clear_episode_buffer()
                successes += success
                if not success:
                    failures[str(seed)] = step_info.get("failure_mode")
                side["tried"].append(seed)
                _write_sidecar(root, side)
            if bar is not None:
                bar.update(kept - bar.n)
                dt = time.perf_counter() - t0
                bar.set_postfix(success=f"{successes}/{len(side['tried']) - len(tried)}",
                                steps_s=f"{env_steps / max(dt, 1e-9):.1f}")
    finally:
        # Ignore further signals while closing: a second Ctrl-C must not corrupt the footer.
        for sig in (signal.SIGINT, signal.SIGTERM):
            with suppress(ValueError):
                signal.signal(sig, signal.SIG_IGN)
        try:
            if ds.has_pending_frames():
                ds.clear_episode_buffer()
            ds.finalize()
            env.close()
            if bar is not None:
                bar.close()
        finally:
            interrupts.restore()

    dt = time.perf_counter() - t0
    return {"episodes": kept, "new_episodes": kept - start_kept, "successes": successes,
            "tried": len(side["tried"]) - len(tried), "failures": failures,
            "env_steps": env_steps, "seconds": dt, "steps_per_s": env_steps / max(dt, 1e-9)}


# ----------------------------------------------------------------------------- replay
def replay(dataset_dir: str | Path, episode: int) -> float:
    """Re-simulate episode `episode` from its stored seed and actions (state-only env).

    Returns the largest absolute difference between the recorded ``observation.state`` and the
    re-simulated ``agent_pos`` over the episode; ~0 because the simulation is deterministic.
    """
    from so101_sim.env import PickPlaceEnv

    root = Path(dataset_dir)
    df = _read_frames(root, ["episode_index", "frame_index", "episode_seed",
                             "observation.state", "action"])
    ep = df[df["episode_index"] == episode].sort_values("frame_index")
    if len(ep) == 0:
        n = df["episode_index"].nunique()
        raise ValueError(f"episode {episode} not in {root} (it has {n} episodes, 0..{n - 1})")
    seed = int(np.asarray(ep["episode_seed"].iloc[0]).reshape(-1)[0])
    states = np.stack([np.asarray(s, dtype=np.float32) for s in ep["observation.state"]])
    actions = np.stack([np.asarray(a, dtype=np.float32) for a in ep["action"]])
    task = _read_sidecar(root).get("task", "pick_place")

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

"""Record scripted-expert demonstrations as a LeRobotDataset v3, and replay them.

Everything is written through lerobot's own API (``LeRobotDataset.create`` / ``resume``,
``add_frame``, ``save_episode``, ``finalize``) so the result loads in lerobot unchanged. Each
frame also carries the episode's reset seed and initial cube pose, so any episode can be
re-simulated exactly (``replay``). A small JSON sidecar in the dataset folder remembers every
seed tried (kept or discarded), the noise level and the codec, so ``resume`` never repeats a
seed and never mixes settings.

Parallel recording (``workers > 1``): each worker process simulates, renders and encodes whole
episodes (its own env and lerobot ``StreamingVideoEncoder``) and hands back the episode's
low-dimensional columns plus one finished mp4 per camera. The parent is the only writer: it
saves episodes in seed order through the same ``save_episode`` path, with the worker's mp4s
standing in for lerobot's streaming encoder (``recording_workers``). The dataset at ``out`` is
therefore a normal LeRobotDataset at every moment, exactly like a one-process recording, and
resume/interrupt work the same way. Seeds go out in increasing order and only while the
episodes kept so far plus those in flight are fewer than wanted, so no surplus episode is ever
recorded and the kept seeds are the same as with one process.

DART noise (``dart_noise > 0``): the env executes the expert's action plus Gaussian noise drawn
from a per-episode stream seeded by the episode seed; ``action`` stays the expert's clean
action (the label) and ``action_executed`` stores what was executed, which ``replay`` uses.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
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
VIDEO_KEYS = tuple(f"observation.images.{cam}" for cam in CAMERAS)
#: Video codecs `record` offers. h264 (libx264 "veryfast", crf 23) costs about half the CPU of
#: lerobot's default AV1 (libsvtav1 preset 12, crf 30) per 480x640 frame at a similar file size
#: and PSNR, and decodes ~3x faster; that is what lets two cores record >= 50 env-steps/s.
VCODECS: dict[str, dict[str, Any]] = {
    "h264": {"vcodec": "h264", "preset": "veryfast", "crf": 23},
    "libsvtav1": {"vcodec": "libsvtav1"},
}
DEFAULT_VCODEC = "h264"
WORKER_TMP = "tmp_workers"  # inside the dataset root: same filesystem, so mp4s move, not copy
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


def _check_args(n_episodes: int, workers: int, seed_start: int, vcodec: str | None) -> None:
    if n_episodes < 1:
        raise ValueError(f"n_episodes={n_episodes}; expected >= 1")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers={workers!r} is invalid; expected an integer >= 1, e.g. "
                         f"--workers {os.cpu_count() or 2} (one per CPU core)")
    if vcodec is not None and vcodec not in VCODECS:
        raise ValueError(f"vcodec={vcodec!r} is not supported; expected one of "
                         f"{sorted(VCODECS)} (--vcodec h264 is the fast default)")
    check_seed_range(seed_start)


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

    def ignore(self) -> None:
        """While closing: a second Ctrl-C must not corrupt the footer."""
        for sig in self._old:
            signal.signal(sig, signal.SIG_IGN)

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
            signum, self.pending = self.pending, None
            raise KeyboardInterrupt(f"signal {signum}")


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


# ----------------------------------------------------------------------------- bookkeeping
@dataclass
class _Tally:
    """Counts, sidecar and progress bar, shared by the one-process and the worker recorder."""

    root: Path
    side: dict[str, Any]
    kept: int
    n_episodes: int
    progress: bool
    start_kept: int = 0
    successes: int = 0
    tried: int = 0
    env_steps: int = 0
    time_physics: float = 0.0
    time_render: float = 0.0
    time_write: float = 0.0  # wall time in the writer: feeding/finishing videos, save_episode
    cpu_seconds: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    bar: Any = None

    def __post_init__(self) -> None:
        self.start_kept = self.kept
        if self.progress:
            from tqdm import tqdm
            self.bar = tqdm(total=self.n_episodes, initial=self.kept, unit="ep", desc="record")

    def episode(self, seed: int, success: bool, failure_mode: str | None, steps: int,
                saved: bool) -> None:
        """Account for one finished episode (call it inside ``_Interrupts.deferred``)."""
        self.kept += saved
        self.successes += success
        self.tried += 1
        self.env_steps += steps
        if not success:
            self.side["failures"][str(seed)] = failure_mode
        self.side["tried"].append(seed)
        _write_sidecar(self.root, self.side)

    def show(self) -> None:
        if self.bar is not None:
            self.bar.update(self.kept - self.bar.n)
            dt = time.perf_counter() - self.t0
            self.bar.set_postfix(success=f"{self.successes}/{self.tried}",
                                 steps_s=f"{self.env_steps / max(dt, 1e-9):.1f}")

    def summary(self, workers: int) -> dict[str, Any]:
        dt = time.perf_counter() - self.t0
        return {"episodes": self.kept, "new_episodes": self.kept - self.start_kept,
                "successes": self.successes, "tried": self.tried,
                "failures": self.side["failures"], "env_steps": self.env_steps, "seconds": dt,
                "steps_per_s": self.env_steps / max(dt, 1e-9), "workers": workers,
                "dart_noise": self.side["dart_noise"], "vcodec": self.side["vcodec"],
                "time_physics": self.time_physics, "time_render": self.time_render,
                "time_write": self.time_write, "cpu_seconds": self.cpu_seconds}


# ----------------------------------------------------------------------------- opening
def _codec_of(features: dict[str, Any]) -> str | None:
    """Codec a dataset's videos were written with (None before the first episode)."""
    info = features.get(VIDEO_KEYS[0], {}).get("info") or {}
    codec = info.get("video.codec")
    return {"av1": "libsvtav1"}.get(codec, codec)


def _resume_settings(root: Path, image_size: tuple[int, int], dart_noise: float,
                     vcodec: str | None, expert: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """Sidecar of the dataset being resumed, and its codec; refuses a mismatch of settings."""
    side = _read_sidecar(root)
    if not (root / "meta" / "info.json").exists():
        raise ValueError(f"{root} is not a LeRobot dataset (no meta/info.json); cannot --resume")
    if side.get("image_size") and tuple(side["image_size"]) != image_size:
        raise ValueError(f"{root} was recorded at {side['image_size'][0]}x"
                         f"{side['image_size'][1]}; resume with --image-size to match")
    features = _features(root)
    old_noise = float(side.get("dart_noise", 0.0))
    if old_noise != dart_noise:
        raise ValueError(f"{root} was recorded with --dart-noise {old_noise:g}, not "
                         f"{dart_noise:g}; resume with --dart-noise {old_noise:g} (a dataset "
                         "holds one noise level)")
    old_expert = side.get("expert", {})
    if old_expert != expert:
        raise ValueError(f"{root} was recorded with expert options {old_expert}, not {expert}; "
                         "resume with the same --recover / --grasp-clearance")
    codec = side.get("vcodec") or _codec_of(features) or vcodec or DEFAULT_VCODEC
    if vcodec is not None and vcodec != codec:
        raise ValueError(f"{root} holds {codec} videos; resume with --vcodec {codec} or "
                         "without --vcodec (videos of one dataset share a codec)")
    return side, codec


def _encoder(vcodec: str, features: dict[str, Any] | None = None) -> Any:
    """lerobot encoder config: the dataset's own settings when it has videos, else ours."""
    from lerobot.configs.video import RGBEncoderConfig

    info = (features or {}).get(VIDEO_KEYS[0], {}).get("info") or {}
    if info.get("video.codec"):
        return RGBEncoderConfig.from_video_info(info)
    return RGBEncoderConfig(**VCODECS[vcodec])


@dataclass
class _Opened:
    ds: Any
    side: dict[str, Any]
    next_seed: int
    encoder_kwargs: dict[str, Any]


def _open_dataset(root: Path, resume: bool, repo_id: str, task_arg: str,
                  image_size: tuple[int, int], seed_start: int, dart_noise: float,
                  vcodec: str | None, queue_size: int, streaming_encoding: bool,
                  expert: dict[str, Any]) -> _Opened:
    """Create the dataset, or reopen it for appending; write the sidecar."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    exists = root.exists() and any(root.iterdir())
    if exists and not resume:
        raise ValueError(f"{root} already exists and is not empty; pass --resume to continue "
                         "recording into it, or choose another --out")
    # Streaming encoding with a queue that holds a whole episode: lerobot's encoder drops
    # frames when its queue is full, which would desynchronise video and data under load.
    writer_kwargs = {"streaming_encoding": streaming_encoding, "encoder_threads": 1,
                     "encoder_queue_maxsize": queue_size}
    if resume and exists:
        side, codec = _resume_settings(root, image_size, dart_noise, vcodec, expert)
        tried = [int(s) for s in side.get("tried", [])] + stored_seeds(root)
        repo_id = side.get("repo_id", repo_id)
        task_arg = side.get("task", task_arg)
        encoder = _encoder(codec, _features(root))
        ds = LeRobotDataset.resume(repo_id, root=root, rgb_encoder=encoder, **writer_kwargs)
        failures = dict(side.get("failures", {}))
        next_seed = max([seed_start - 1, *tried]) + 1
    else:
        if root.exists():
            root.rmdir()  # empty: lerobot insists on creating the folder itself
        codec = vcodec or DEFAULT_VCODEC
        encoder = _encoder(codec)
        ds = LeRobotDataset.create(repo_id=repo_id, fps=30, root=root, robot_type=ROBOT_TYPE,
                                   features=dataset_features(image_size, dart_noise > 0),
                                   use_videos=True, rgb_encoder=encoder, **writer_kwargs)
        tried, failures, next_seed = [], {}, seed_start
    side = {"repo_id": repo_id, "task": task_arg, "image_size": list(image_size),
            "dart_noise": dart_noise, "vcodec": codec, "tried": sorted(set(tried)),
            "failures": failures, "expert": expert}
    _write_sidecar(root, side)
    return _Opened(ds, side, next_seed, dataclasses.asdict(encoder))


def _task_arg(task: str | Path, root: Path, resume: bool) -> str:
    """The task as stored in the sidecar: a name, or an absolute .toml path."""
    if resume and (root / SIDECAR).exists():
        return str(_read_sidecar(root).get("task", task))
    return str(Path(task).resolve()) if Path(str(task)).suffix == ".toml" else str(task)


# ----------------------------------------------------------------------------- record
def _quiet_libav() -> None:
    """Hide libav's info chatter (x264's per-file statistics, remux notes) on the console."""
    import av

    av.logging.set_libav_level(av.logging.WARNING)


def record(out_dir: str | Path, n_episodes: int, task: str | Path = "pick_place",
           seed_start: int = 0, image_size: tuple[int, int] = (480, 640),
           keep_failures: bool = False, resume: bool = False, workers: int = 1,
           repo_id: str = DEFAULT_REPO_ID, progress: bool = True,
           streaming_encoding: bool = True, dart_noise: float = 0.0,
           vcodec: str | None = None, recover: bool = False,
           grasp_clearance: float | None = None) -> dict[str, Any]:
    """Record `n_episodes` expert episodes (only successes unless `keep_failures`) to `out_dir`.

    Seeds run upward from `seed_start` (or, with `resume`, from after the largest seed already
    tried); episodes are stored in seed order whatever `workers` is. Each episode is saved as
    soon as it (and every lower seed) ends, and the dataset is finalized on any exit, including
    Ctrl-C / SIGTERM, so an interrupted run loads with every completed episode. `vcodec` is
    ``"h264"`` (default for new datasets) or ``"libsvtav1"``; a resumed dataset keeps its own.
    `workers` > 1 records in that many processes (see the module docstring); `dart_noise` is
    the std of the noise added to executed actions (``run_episode``), 0 for none; `recover`
    and `grasp_clearance` are ScriptedExpert options (retries; gap between the fixed pad and
    the cube at the grasp, metres), stored with the dataset. Returns a
    summary dict (episodes, successes, tried, env_steps, steps_per_s, seconds, and the
    time_physics / time_render / cpu_seconds spent by all recording processes).
    """
    from so101_sim.task import load_task

    _check_args(n_episodes, workers, seed_start, vcodec)
    dart_noise = check_dart_noise(dart_noise)
    expert = expert_options(recover, grasp_clearance)
    _quiet_libav()
    from so101_sim.rendering import select_gl_backend

    select_gl_backend()  # choose (and print) once here: worker processes inherit MUJOCO_GL
    root = Path(out_dir)
    image_size = (int(image_size[0]), int(image_size[1]))
    task_arg = _task_arg(task, root, resume)
    spec = load_task(task_arg)
    if spec.fps != 30:
        raise ValueError(f"task fps is {spec.fps}; the dataset is recorded at 30 fps")
    opened = _open_dataset(root, resume, repo_id, task_arg, image_size,
                           seed_start, dart_noise, vcodec, spec.max_steps + 2,
                           streaming_encoding or workers > 1, expert)
    tally = _Tally(root, opened.side, opened.ds.meta.total_episodes, n_episodes, progress)
    if workers == 1:
        _record_here(opened, tally, keep_failures, image_size)
    else:
        from so101_sim.recording_workers import record_with_workers

        record_with_workers(opened, tally, keep_failures, image_size, workers, spec)
    return tally.summary(workers)


def _record_here(opened: _Opened, tally: _Tally, keep_failures: bool,
                 image_size: tuple[int, int]) -> None:
    """One process: simulate, render and feed lerobot's own streaming encoder."""
    from so101_sim.env import PickPlaceEnv
    from so101_sim.expert import ScriptedExpert

    ds, side = opened.ds, opened.side
    env = PickPlaceEnv(task=side["task"], obs_type="pixels_agent_pos_env_state",
                       image_size=image_size)
    expert = ScriptedExpert(env.task, **side["expert"])
    next_seed, cpu0 = opened.next_seed, time.process_time()
    interrupts = _Interrupts()
    interrupts.install()

    def add_frame(frame: dict[str, Any]) -> None:
        t = time.perf_counter()
        ds.add_frame(frame)
        tally.time_write += time.perf_counter() - t

    try:
        while tally.kept < tally.n_episodes:
            seed = next_seed
            check_seed_range(seed)
            next_seed += 1
            success, mode, steps = run_episode(env, expert, seed, add_frame,
                                               side["dart_noise"])
            with interrupts.deferred():
                t = time.perf_counter()
                keep = success or keep_failures
                if keep:
                    ds.save_episode()
                else:
                    ds.clear_episode_buffer()
                tally.time_write += time.perf_counter() - t
                tally.episode(seed, success, mode, steps, keep)
            tally.show()
    finally:
        interrupts.ignore()
        try:
            tally.time_physics, tally.time_render = env.time_physics, env.time_render
            tally.cpu_seconds = time.process_time() - cpu0
            _close(ds, tally)
            env.close()
        finally:
            interrupts.restore()


def _close(ds: Any, tally: _Tally) -> None:
    if ds.has_pending_frames():
        ds.clear_episode_buffer()
    ds.finalize()
    if tally.bar is not None:
        tally.bar.close()


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

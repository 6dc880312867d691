"""Closed-loop evaluation: K env workers, batched policy calls, results on disk.

An env that has used up its action chunk sends its last ``n_obs_steps`` observations and waits;
as soon as the policy's batch is full (or no other env can still ask), one ``predict_chunks``
call answers the waiting envs and each worker executes its chunk (``n_action_steps`` actions).
With more envs than rows per forward, the others step and render while the policy runs.
An episode's outcome depends only on its seed, the policy and the task: episodes start from
their seed, the policy's per-episode state is per slot and seeded by the episode seed, and the
lerobot adapter keeps batched inference bitwise independent of which envs share a batch.
The workers come from ``so101_sim.workers`` (local processes or Ray actors): the loop below
is the same on both, and so are the results. ``save_rollouts`` also writes every episode into a
LeRobotDataset (``so101_sim.harness.rollouts``); without it nothing here changes.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.dataset import EVAL_SEED_START, check_video_size
from so101_sim.dataset.interrupts import Interrupts
from so101_sim.harness.env_worker import EnvWorkerConfig
from so101_sim.harness.eval_args import check_eval_args
from so101_sim.harness.forwards import Forwards, forward_stats
from so101_sim.harness.frames import Rendering, choose_rendering, to_policy_obs, with_cameras
from so101_sim.harness.policies import ChunkRequest, EvalPolicy, load_policy
from so101_sim.harness.results import (
    EpisodeRecord,
    RunDir,
    aggregate,
    lock_eval_folders,
    per_episode,
    summary_line,
)
from so101_sim.harness.trained_on import check_unseen_seeds
from so101_sim.harness.warmup import worker_preload
from so101_sim.tasks import DEFAULT_TASK, TaskSpec, load_task, task_ref
from so101_sim.utils.devices import eval_policy_threads, torch_threads, workers_that_fit
from so101_sim.utils.disk import note_default_out
from so101_sim.utils.locks import lock_scope
from so101_sim.utils.text import counted, seed_span
from so101_sim.utils.versions import run_setup
from so101_sim.workers import PoolInfo, Reply, check_backend, start_pool


@dataclass
class _Slot:
    """The episode running in one worker, as the parent sees it."""

    seed: int | None = None
    episode_ix: int = 0
    video: str | None = None
    history: deque = field(default_factory=deque)
    t0: float = 0.0
    steps: int = 0
    rewards: list[float] = field(default_factory=list)
    physics_s: float = 0.0
    render_s: float = 0.0
    policy_s: float = 0.0


@lock_scope  # releases the folder locks lock_eval_folders takes
def evaluate(policy: EvalPolicy | str, *, task: str | Path | TaskSpec = DEFAULT_TASK,
             episodes: int = 50,
             n_envs: int = 16, seed_start: int = EVAL_SEED_START, out_dir: str | Path | None = None,
             videos: int = 2, image_size: tuple[int, int] | None = None, resume: bool = False,
             allow_train_seeds: bool = False, worker_timeout_s: float = 600.0,
             max_retries: int = 2, progress: bool = True, report: bool = True,
             backend: str = "local", ray_address: str | None = None,
             save_rollouts: str | Path | None = None, checkpoint_every: int = 50,
             threads: int | None = None, faithful: bool = False, stop: Any = None,
             log: Callable[[str], None] = print) -> dict[str, Any]:
    """Evaluate `policy` on `episodes` seeds from `seed_start`; return the eval_info dict.

    `policy` is an ``EvalPolicy``, ``"expert"`` or a lerobot checkpoint directory. Writes
    episodes.jsonl (as episodes end), eval_info.json, videos of the first `videos` episodes
    and report.md/report.png into `out_dir` (default outputs/eval/<policy>-<task>-<time>).
    `backend`: where the envs run, ``"local"`` (processes here) or ``"ray"`` (Ray actors; a
    local Ray runtime, or the cluster at `ray_address`: ``"auto"`` or ``host:port``). Results
    per seed do not depend on it; policy forwards always run batched in this process.
    `save_rollouts`: a folder that gets every evaluated episode as a LeRobotDataset, written in
    seed order and checkpointed every `checkpoint_every` episodes (``harness.rollouts``);
    every step is then rendered, so the run is slower, but its results are the same.
    `threads`: torch CPU threads for the policy's forwards while it runs (restored after);
    None: ``devices.eval_policy_threads()``, half the cores (one on 2 cores).
    `faithful`: render at the training data's size (else the smallest size that passes the
    self-check in ``harness.frames``). `stop`: an object with ``update(done) -> bool``,
    asked first (resumed episodes) and after each new one, and ``to_info()`` (harness.against).
    """
    spec = load_task(task)  # parsed once here; the spec travels to the workers
    if not isinstance(policy, EvalPolicy):
        policy = load_policy(policy, task=spec)
    check_eval_args(episodes=episodes, n_envs=n_envs, seed_start=seed_start, videos=videos,
                    allow_train_seeds=allow_train_seeds, image_size=image_size, threads=threads,
                    worker_timeout_s=worker_timeout_s, max_retries=max_retries,
                    checkpoint_every=checkpoint_every)
    check_backend(backend, ray_address)
    info = policy.info
    check_unseen_seeds(info.demos, spec, range(seed_start, seed_start + episodes),
                       allow_train_seeds)
    if info.cameras and not faithful and not image_size:
        from so101_sim.sim.rendering import select_gl_backend

        select_gl_backend()  # the self-check renders here, before the workers exist
    rendering = choose_rendering(info, image_size, task=spec, faithful=faithful, log=log)
    if info.camera_map:  # inputs named after another rig: say which env camera feeds which
        from so101_sim.harness.camera_map import describe_camera_map

        rendering.label += f"; cameras: {describe_camera_map(info.camera_map)}"
    if out_dir is None:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        out_dir = Path("outputs/eval") / f"{info.name}-{spec.name}-{stamp}"
        note_default_out(out_dir)  # the command that resumes it names this folder
    run = RunDir(out_dir)
    lock_eval_folders(run.path, save_rollouts)  # another run writing them: refused here
    identity = {
        "policy": info.name, "policy_fingerprint": info.fingerprint, "task": spec.name,
        "task_sha256": spec.sha256(),
        "seed_start": seed_start, "episodes": episodes,
        "render_size": list(rendering.render_size), "mesh_width": rendering.mesh_width,
        "policy_image_size": list(rendering.input_size) if rendering.input_size else None,
    }
    spec = with_cameras(spec, info.cameras)  # after the identity: the task is the same one
    if save_rollouts is not None:  # absolute: a resume from another folder still matches
        identity["save_rollouts"] = str(Path(save_rollouts).expanduser().resolve())
    if resume and run.config_path.exists():
        from so101_sim.harness.rollouts import check_resume_target

        check_resume_target(run.path, run.config_path, identity.get("save_rollouts"))
    sink = None
    if save_rollouts is not None:  # checked before the run folder is touched
        from so101_sim.harness.rollouts import rollout_sink

        check_video_size(tuple(rendering.render_size), "--save-rollouts: the render size")

        sink = rollout_sink(
            save_rollouts, resume=resume, spec=spec, image_size=tuple(rendering.render_size),
            task_arg=task_ref(spec), seeds=list(range(seed_start, seed_start + episodes)),
            eval_out=run.path, identity=identity, checkpoint_every=checkpoint_every)
    # More episodes on --resume extend the run (same seeds first); not with a rollouts
    # dataset, whose seed list is fixed when it is created.
    grow = ("episodes",) if save_rollouts is None else ()
    if backend == "ray":  # SIGTERM exits 15 and cleans up from the run folder's first file on
        from so101_sim.workers.ray_connect import exit_on_sigterm

        exit_on_sigterm()
    setup = run_setup()  # episodes finished with another one get a note (actions differ)
    done = {s: r for s, r in run.prepare(identity, resume, may_grow=grow, setup=setup).items()
            if seed_start <= s < seed_start + episodes}
    if note := run.setup_note():
        log(note)
    if sink is not None:
        done = _open_rollouts(sink, resume, done, save_rollouts, log)
    todo = deque(s for s in range(seed_start, seed_start + episodes) if s not in done)
    if stop is not None and done and stop.update(done):  # a resumed run may be decided
        todo.clear()
    log(f"so101-sim eval: {info.name} on {spec.name}, "
        f"{seed_span(seed_start, seed_start + episodes - 1)} ({len(done)} done, {len(todo)} to "
        f"run), {counted(min(n_envs, max(1, len(todo))), 'env')}; images: {rendering.label}")
    t_start = time.perf_counter()
    n_run, workers = 0, PoolInfo(backend, 0)
    forwards_seen = forward_stats()
    reruns: list[dict[str, Any]] = []
    finished = False
    # Ctrl-C and SIGTERM (`timeout`, a cancelled job) end with the CLI's resume line, not a
    # silent kill; the loop asks each turn for one dropped during garbage collection.
    own = Interrupts.of_defaults() if sink is None else None
    interrupts = sink.interrupts if sink is not None else own
    if own is not None:
        own.install()
    try:
        if todo:
            with torch_threads(eval_policy_threads(threads, log)):
                n_run, workers, forwards_seen = _run(
                    policy, run, spec, rendering, todo, done, seed_start, episodes, n_envs,
                    videos, worker_timeout_s, max_retries, progress, backend, ray_address,
                    reruns, log, sink, stop, interrupts.check if interrupts else None)
        finished = True
    finally:
        if sink is not None:
            sink.close(finished)
        if own is not None:
            own.restore()
    eval_s = time.perf_counter() - t_start

    records = [done[s] for s in sorted(done)]
    aggregated = aggregate(records, eval_s, n_run)
    result = {
        "per_episode": per_episode(records),
        "aggregated": aggregated,
        "config": {**identity, "n_envs": n_envs, "images": rendering.label,
                   "policy_details": info.details, "workers": workers.to_dict(),
                   **({"policy_weights": info.weights} if info.weights else {}),
                   **forwards_seen, **setup, **run.earlier_setups(),
                   "reruns": reruns, "video_paths": [r.video for r in records if r.video],
                   **({"image_check": rendering.check} if rendering.check else {})},
    }
    if stop is not None:
        result["sequential_verdict"] = stop.to_info()
    result["summary"] = summary_line(info.name, spec.name, aggregated, run.path,
                                     images=rendering.label)
    run.write_info(result)
    if report:
        from so101_sim.harness.report import write_report

        write_report(run.path, result, records)
    log(result["summary"])
    return result


def _open_rollouts(sink: Any, resume: bool, done: dict[int, EpisodeRecord],
                   save_rollouts: str | Path, log: Callable[[str], None]
                   ) -> dict[int, EpisodeRecord]:
    """Open the rollout dataset; finished episodes missing from it run again (same seed, same
    episode), so it ends with every seed exactly once. Returns the episodes still done."""
    from so101_sim.harness.rollouts import open_sink

    open_sink(sink, resume)
    missing = sorted(s for s in done if not sink.has(s))
    if missing:
        are, them = ("is", "it") if len(missing) == 1 else ("are", "them")
        log(f"so101-sim eval: {counted(len(missing), 'finished episode')} {are} not in "
            f"--save-rollouts {save_rollouts} (first: seed {missing[0]}); running {them} "
            f"again to record {them}")
    return {s: r for s, r in done.items() if s not in missing}


def _run(policy: EvalPolicy, run: RunDir, task: TaskSpec, rendering: Rendering, todo: deque,
         done: dict[int, EpisodeRecord], seed_start: int, episodes: int, n_envs: int,
         videos: int, worker_timeout_s: float, max_retries: int, progress: bool,
         backend: str, ray_address: str | None, reruns: list[dict[str, Any]],
         log: Callable[[str], None], sink: Any = None, stop: Any = None,
         check: Callable[[], None] | None = None) -> tuple[int, PoolInfo, dict[str, Any]]:
    """Run every seed in `todo`; add each finished episode to `done` and to the run folder
    (and, with a rollout `sink`, to its dataset), and each episode that had to be run again
    to `reruns`. Returns (episodes run, workers, forward stats: the most forwards in flight
    at once, and the policy rows used and computed)."""
    from tqdm import tqdm

    info = policy.info
    cfg = EnvWorkerConfig(task=task, render_size=rendering.render_size, cameras=info.cameras,
                          env_state=info.needs_env_state, n_obs_steps=info.n_obs_steps,
                          rollout=sink.tape if sink is not None else None,
                          mesh_width=rendering.mesh_width,
                          resize_to=rendering.input_size if rendering.resize else None)
    failures: Counter[int] = Counter()
    pad_to = int(getattr(policy, "batch_size", 0) or 0)
    if n_envs < pad_to:
        fill = "fills" if n_envs == 1 else "fill"
        log(f"so101-sim eval: {counted(n_envs, 'env')} {fill} at most {n_envs} of each "
            f"{pad_to}-row policy forward, the rest is padding (actions per seed stay those "
            f"of any --n-envs); --n-envs {pad_to} or more puts those rows to use")
    if info.cameras or videos or sink is not None:
        from so101_sim.sim.rendering import select_gl_backend

        select_gl_backend()  # choose (and print) once here: workers inherit MUJOCO_GL
    bar = tqdm(total=episodes, initial=len(done), unit="ep", disable=not progress,
               dynamic_ncols=True)
    n_run = 0
    preload = worker_preload(resize=cfg.resize_to is not None, rollouts=sink is not None,
                             videos=videos > 0)
    n_workers = min(n_envs, len(todo))
    pool = start_pool(cfg, workers_that_fit(n_workers, log) if backend == "local" else n_workers,
                      backend=backend, ray_address=ray_address, name="so101-eval-worker",
                      preload=preload, timeout_s=worker_timeout_s, log=log)
    slots = [_Slot() for _ in range(pool.size)]
    # Rows per policy forward: the policy's own batch size (LeRobotPolicy pads to it), else all.
    batch = pad_to or pool.size
    waiting: deque[int] = deque()  # slots that need a chunk, in the order they asked

    def fail(i: int, why: str) -> None:
        s = slots[i]
        seed = s.seed
        run.append(EpisodeRecord(seed=seed, episode_ix=s.episode_ix, status="error",
                                 steps=s.steps, seconds=time.perf_counter() - s.t0, error=why))
        slots[i] = _Slot()
        failures[seed] += 1
        reruns.append({"seed": seed, "error": why.strip().splitlines()[0]})
        if failures[seed] > max_retries:
            raise RuntimeError(f"episode with seed {seed} failed {failures[seed]} times; last "
                               f"error: {why.strip()}")
        bar.write(f"so101-sim eval: seed {seed}: {why.splitlines()[0]}; running it again")
        todo.appendleft(seed)

    def handle(replies: list[Reply]) -> None:
        nonlocal n_run
        for r in replies:
            i, s, reply = r.worker, slots[r.worker], r.value
            if r.failed:
                fail(i, r.failed)
                continue
            s.physics_s += reply["physics_s"]
            s.render_s += reply["render_s"]
            s.steps += reply.get("steps", 0)
            s.rewards += reply.get("rewards", [])
            if reply.get("done"):
                rec = EpisodeRecord(
                    seed=s.seed, episode_ix=s.episode_ix, success=reply["success"],
                    failure_mode=reply["failure_mode"], steps=s.steps,
                    sum_reward=float(sum(s.rewards)), max_reward=float(max(s.rewards)),
                    seconds=time.perf_counter() - s.t0, physics_s=s.physics_s,
                    render_s=s.render_s, policy_s=s.policy_s,
                    video=run.save_video(s.video, reply.get("video_mp4")),
                    actions_sha=reply["actions_sha"])
                if sink is not None:  # spooled before its line: a kill loses neither
                    sink.add(reply["rollout"], lambda rec=rec: run.append(rec))
                else:
                    run.append(rec)
                done[rec.seed] = rec
                n_run += 1
                slots[i] = _Slot()
                bar.update(1)
                rate = 100.0 * sum(e.success for e in done.values()) / len(done)
                bar.set_postfix_str(f"success {rate:.1f}%")
                if stop is not None and stop.update(done):
                    todo.clear()  # decided: episodes still running are dropped
                    slots[:] = [_Slot() for _ in slots]
                    waiting.clear()
                    return
                continue
            t0 = time.perf_counter()
            new = [to_policy_obs(o, rendering) for o in reply["history"]]
            s.policy_s += time.perf_counter() - t0  # image preprocessing counts as policy
            if not s.history:  # episode start: repeat the first observation To times
                new = new * info.n_obs_steps
            s.history = deque([*s.history, *new], maxlen=info.n_obs_steps)
            waiting.append(i)

    def forward_done() -> None:
        for requests, tokens, actions, seconds in forwards.finished():
            actions = np.asarray(actions, dtype=np.float32)
            want = (len(requests), info.n_action_steps, 6)
            if actions.shape != want:
                raise RuntimeError(f"policy {info.name!r} returned actions of shape "
                                   f"{actions.shape}; expected {want} (requests, "
                                   "n_action_steps, joints)")
            for j, (r, token) in enumerate(zip(requests, tokens, strict=True)):
                if slots[r.slot] is not token:  # that episode ended meanwhile (decided, lost)
                    continue
                token.policy_s += seconds / len(requests)
                pool.submit(r.slot, "act", actions[j])

    # Two forwards in flight where the policy allows it (harness.forwards); else one.
    forwards = Forwards(policy, concurrent=backend == "local"
                        and Forwards.pair_helps(pool.size, batch)
                        and bool(getattr(policy, "concurrent_forwards", False)),
                        pad_to=pad_to)
    try:
        while todo or any(s.seed is not None for s in slots):
            if check is not None:
                check()
            for i, s in enumerate(slots):
                if s.seed is None and todo:
                    seed = todo.popleft()
                    ix = seed - seed_start
                    video = run.video_path(ix, seed) if ix < videos else None
                    slots[i] = _Slot(seed=seed, episode_ix=ix, t0=time.perf_counter(),
                                     video=str(video) if video else None)
                    policy.start_episode(i, seed)
                    pool.submit(i, "reset", seed, slots[i].video is not None)
            forward_done()
            # A forward as soon as it is full (or no env is stepping, so no row can join it):
            # with more envs than rows per forward, the others step while the policy runs.
            if forwards.should_launch(len(waiting), batch, envs_stepping=pool.busy > 0):
                ready = [waiting.popleft() for _ in range(min(batch, len(waiting)))]
                forwards.launch([ChunkRequest(i, slots[i].seed, list(slots[i].history))
                                 for i in ready], [slots[i] for i in ready],
                                alone=not pool.busy)
                continue
            if forwards.inflight and not pool.busy:
                forwards.wait()
                continue
            handle(pool.collect(wait_all=False, wake=forwards.wake))
        workers = pool.info()
    finally:
        forwards.close()
        pool.close()
        bar.close()
    return n_run, workers, forwards.stats()

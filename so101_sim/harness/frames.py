"""How camera frames reach the policy: what size to render at, and the resize to its input.

A checkpoint trained here records the size its demos were rendered at (``train_image_size``)
and its input size (``image_size``, e.g. 60x80). Rendering at the recorded size and resizing
like training did is the *faithful* path (``--faithful``). Rendering costs pixels on a CPU, and
a 480x640 frame shrunk to 60x80 keeps little of them, so by default ``choose_rendering`` takes
the smallest size ``input x k`` (k = 1, 2, 3, ...) whose resized frames match the faithful
ones within ``TOLERANCE`` on a few reset frames of the run's own task and cameras (a
self-check of about 3 s the first time in a process, kept for later evaluations with the same
inputs), and says so in one line. The scene keeps the mesh detail of the recorded width
(``SO101Env(mesh_width=...)``), so the smaller render shows the policy the same geometry.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from so101_sim.harness.policies import PolicyInfo
from so101_sim.tasks import TaskSpec

VIDEO_ONLY_SIZE = (240, 320)  # render size for videos of policies that use no cameras
#: The default's acceptance rule, in grey levels (0..255) of the policy-size frames: mean and
#: 99th percentile of |reduced - faithful|. On the pick_place reset frame a 240x320 render
#: differs from the 480x640 one by 0.25 / 6, a 120x160 one by 0.86 / 14 (DESIGN 12); over the
#: self-check's 8 frames 180x240 differs by 0.40 / 8, so the shipped policy renders there.
TOLERANCE = {"mean": 0.5, "p99": 8.0}
CHECK_SEEDS = (100_000, 100_001, 100_002, 100_003)  # reset frames compared by the self-check
#: Self-checks started ahead (``expect_self_check``), by their inputs (``check_key``).
_AHEAD: dict[tuple, Any] = {}
#: Answers found in this process, by their inputs: the check renders fixed reset frames, so a
#: second evaluation with the same inputs (the next checkpoint of a curve) gets the same one.
_ANSWERS: dict[tuple, tuple] = {}


@dataclass
class Rendering:
    """How camera frames reach the policy; ``label`` goes into the summary and report."""

    render_size: tuple[int, int]
    input_size: tuple[int, int] | None
    label: str
    mesh_width: int | None = None  # mesh detail of this image width (None: the render's)
    check: dict[str, Any] = field(default_factory=dict)  # the self-check's numbers, if any

    @property
    def resize(self) -> bool:
        return self.input_size is not None and self.render_size != self.input_size


def with_cameras(task: TaskSpec, cameras: tuple[str, ...]) -> TaskSpec:
    """`task` rendering `cameras` too, after its own: a policy may read a camera the task does
    not film by default (the wrist), and its videos and saved rollouts then show it as well."""
    extra = tuple(c for c in cameras if c not in task.cameras)
    return dataclasses.replace(task, cameras=task.cameras + extra) if extra else task


def choose_rendering(info: PolicyInfo, image_size: tuple[int, int] | None,
                     task: TaskSpec | None = None, faithful: bool = False,
                     log: Callable[[str], None] = print) -> Rendering:
    """Explicit `image_size` wins; else faithful (`faithful`, or no `task` to check on), else
    the smallest render that passes the self-check against the faithful one. `faithful` with
    an `image_size` other than the recorded one is refused: one of them would be ignored."""
    if not info.cameras:
        size = tuple(image_size) if image_size else VIDEO_ONLY_SIZE
        # --faithful has no training frames to match here: said, so it is not taken for done.
        moot = "; --faithful changes nothing" if faithful else ""
        return Rendering(size, None, f"no camera input (state only{moot}); videos rendered at "
                                     f"{_hw(size)}")
    inp = tuple(info.image_size)
    recorded = tuple(info.train_image_size or inp)
    if image_size and faithful and tuple(image_size) != recorded:
        raise ValueError(f"--faithful renders at the training data's {_hw(recorded)}, but "
                         f"--image-size asks for {_hw(tuple(image_size))}; drop one of them")
    if image_size:
        return _fixed(info, tuple(image_size), inp)
    candidates = _candidates(inp, recorded)
    if faithful or task is None or not candidates:
        return _fixed(info, recorded, inp)
    key = check_key(task, info.cameras, recorded, inp)
    try:
        if key not in _ANSWERS:
            ahead = _AHEAD.pop(key, None)
            answer = ahead.result() if ahead is not None else None
            _ANSWERS[key] = answer or _self_check(task, info.cameras, recorded, inp,
                                                  candidates)
        chosen, check = copy.deepcopy(_ANSWERS[key])
    except Exception as exc:  # no GL in this process, say: the faithful path always works
        log(f"so101-sim eval: images: the render-size self-check failed "
            f"({type(exc).__name__}: {str(exc)[:120]}); rendering faithfully at {_hw(recorded)}")
        return _fixed(info, recorded, inp)
    if chosen is None:
        log(f"so101-sim eval: images: no smaller render matches the faithful {_hw(recorded)} "
            f"within the tolerance (smallest difference: {_stats(check['tried'][-1])}); "
            "rendering faithfully")
        return Rendering(recorded, inp, _fixed(info, recorded, inp).label, check=check)
    stats = _stats(check["tried"][-1])
    label = (f"reduced: rendered at {_hw(chosen)} (mesh detail of the recorded {recorded[1]} "
             f"px width), resize_frames to {_hw(inp)}; vs the faithful {_hw(recorded)}: "
             f"{stats}")
    log(f"so101-sim eval: images: rendering at {_hw(chosen)} instead of the recorded "
        f"{_hw(recorded)} ({stats} after resizing to {_hw(inp)}; tolerance mean "
        f"{TOLERANCE['mean']}, p99 {TOLERANCE['p99']}); --faithful renders at {_hw(recorded)}")
    return Rendering(chosen, inp, label, mesh_width=recorded[1], check=check)


def _fixed(info: PolicyInfo, size: tuple[int, int], inp: tuple[int, int]) -> Rendering:
    if size == inp:
        label = f"direct: rendered at the policy's input size {_hw(inp)}, no resize"
        if info.train_image_size and tuple(info.train_image_size) != inp:
            label += (f" (training frames were recorded at {_hw(info.train_image_size)} and "
                      "resized: fast path, not the faithful one)")
        return Rendering(size, inp, label)
    label = f"resized: rendered at {_hw(size)}, resize_frames to {_hw(inp)}"
    if info.train_image_size and tuple(info.train_image_size) == size:
        label = f"faithful: rendered at the training data's {_hw(size)}, resize_frames to " \
                f"{_hw(inp)}"
    elif info.train_image_size:  # frames resized to the input: keep the training geometry
        recorded = tuple(info.train_image_size)
        label += (f" (mesh detail of the recorded {recorded[1]} px width; training data was "
                  f"recorded at {_hw(recorded)})")
        return Rendering(size, inp, label, mesh_width=recorded[1])
    return Rendering(size, inp, label)


def _candidates(inp: tuple[int, int], recorded: tuple[int, int]) -> list[tuple[int, int]]:
    """input x 1, 2, 3, ... below the recorded size, smallest first (same aspect only): an
    integer multiple shrinks by a whole factor, and every one is tried, since render cost
    grows with pixels (x3 costs 15% less a chunk than x4 for the shipped policy)."""
    if recorded[0] * inp[1] != recorded[1] * inp[0]:
        return []
    return [(inp[0] * k, inp[1] * k) for k in range(1, -(-recorded[0] // inp[0]))]


def check_key(task: TaskSpec, cameras: tuple[str, ...], recorded: tuple[int, int],
              inp: tuple[int, int]) -> tuple:
    """Everything a self-check's answer depends on (the task by its contents)."""
    return task.sha256(), tuple(cameras), tuple(recorded), tuple(inp)


def self_check(task: TaskSpec, cameras: tuple[str, ...], recorded: tuple[int, int],
               inp: tuple[int, int]) -> tuple[tuple[int, int] | None, dict[str, Any]]:
    """The render size ``choose_rendering`` would pick and its numbers (run anywhere)."""
    return _self_check(task, cameras, recorded, inp, _candidates(inp, recorded))


def expect_self_check(key: tuple, pending: Any) -> None:
    """Register a self-check started ahead: `pending.result()` returns what ``self_check``
    returned for the inputs `key` describes, or None (then it is run here after all)."""
    _AHEAD[key] = pending


def _frames(task: TaskSpec, cameras: tuple[str, ...], size: tuple[int, int],
            mesh_width: int, input_size: tuple[int, int]) -> np.ndarray:
    """Reset frames of CHECK_SEEDS, every camera, resized to the policy's input (uint8)."""
    from so101_sim.sim import SO101Env
    from so101_sim.utils.image_pipeline import resize_frames

    env = SO101Env(task, obs_type="state", image_size=size, render_mode="rgb_array",
                   cameras=cameras, mesh_width=mesh_width)
    try:
        shots = []
        for seed in CHECK_SEEDS:
            env.reset(seed=seed)
            frame = env.render()
            w = size[1]
            shots += [frame[:, i * w:(i + 1) * w] for i in range(len(cameras))]
    finally:
        env.close()
    return resize_frames(np.stack(shots), input_size).numpy()


def _self_check(task: TaskSpec, cameras: tuple[str, ...], recorded: tuple[int, int],
                inp: tuple[int, int], candidates: list[tuple[int, int]]
                ) -> tuple[tuple[int, int] | None, dict[str, Any]]:
    reference = _frames(task, cameras, recorded, recorded[1], inp).astype(np.int16)
    tried = []
    for size in candidates:
        diff = np.abs(_frames(task, cameras, size, recorded[1], inp).astype(np.int16)
                      - reference)
        row = {"size": list(size), "mean": float(diff.mean()),
               "p99": float(np.percentile(diff, 99)), "max": int(diff.max()),
               "frames": len(diff)}
        tried.append(row)
        if row["mean"] <= TOLERANCE["mean"] and row["p99"] <= TOLERANCE["p99"]:
            return size, {"faithful_size": list(recorded), "tolerance": TOLERANCE,
                          "tried": tried}
    return None, {"faithful_size": list(recorded), "tolerance": TOLERANCE, "tried": tried}


def _stats(row: dict[str, Any]) -> str:
    return (f"mean |diff| {row['mean']:.2f}, p99 {row['p99']:.0f}, max {row['max']} grey "
            f"levels over {row['frames']} frames")


def _hw(size: Any) -> str:
    return f"{size[0]}x{size[1]}"


def to_policy_obs(obs: dict[str, Any], rendering: Rendering) -> dict[str, Any]:
    """Resize a worker's frames to the policy's input size with the training resize (frames a
    worker already resized, ``EnvWorkerConfig.resize_to``, pass through)."""
    if "pixels" not in obs or not rendering.resize:
        return obs
    cams = list(obs["pixels"])
    if cams and obs["pixels"][cams[0]].shape[:2] == tuple(rendering.input_size):
        return obs
    from so101_sim.utils.image_pipeline import resize_pixels

    return {**obs, "pixels": resize_pixels(obs["pixels"], rendering.input_size)}

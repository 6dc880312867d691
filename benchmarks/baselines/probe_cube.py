"""Can a checkpoint's image encoder tell where the cube is? A linear probe, per bearing bin.

    .venv/bin/python benchmarks/baselines/probe_cube.py policy/suite_diffusion \
        ~/so101-runs/runs/anywhere_scratch_cpu/checkpoints/step_0020000/pretrained_model \
        --task pick_place_anywhere --seeds 400

For each seed (from ``--seed-start``, away from the evaluation seeds) the scripted expert runs
in the env, and two moments are kept: the reset frame, and one frame on the way to the grasp
(a seeded step of the expert's approach or descent, the gripper open over the cube). Each
frame goes through the checkpoint's own preprocessor and its Diffusion encoder (eval mode: the
centre crop, both cameras), as in a rollout, giving the feature vector the U-Net is
conditioned on. Ridge regressions, fitted with 5-fold cross-validation over seeds, read from
those features the cube's position on the table at reset, and the cube's offset from the
gripper's tool-centre point on the approach. The table gives the held-out error per bearing
bin (equal-count bins around the pan axis, the robot's right first, as ``by_place.py``).

An encoder that sees the cube equally well everywhere has flat errors across bins; a bin the
policy fails in with a larger error here points at what the cameras show there (or how the
encoder pools it), a flat one at what the policy does with what it sees. ``--random`` adds a
randomly initialised encoder of the first checkpoint's shape as a floor to read against.
``--keypoints`` also probes each encoder one step earlier: its SpatialSoftmax keypoints (32
expected (x, y) positions per camera), before the linear layer and ReLU that the U-Net's
conditioning passes through.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from so101_sim.expert import ScriptedExpert
from so101_sim.harness.policies.lerobot import LeRobotPolicy
from so101_sim.sim import PickPlaceEnv
from so101_sim.tasks.layouts import PAN_AXIS_XY
from so101_sim.utils.image_pipeline import resize_frames

ON_THE_WAY = ("approach", "descend")  # phases whose frames the approach probe reads


def collect(task: str, seeds: list[int], render: tuple[int, int]) -> dict[str, np.ndarray]:
    """Per seed: frames (reset, on the way), the targets and the cube's bearing."""
    env = PickPlaceEnv(task=task, obs_type="pixels_agent_pos_env_state", image_size=render)
    expert = ScriptedExpert(task, model=env.model)
    out: dict[str, list] = {k: [] for k in ("reset", "way", "cube_xy", "offset", "bearing")}
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            expert.reset(seed)
            x, y = env.cube_pos()[:2]
            out["bearing"].append(math.degrees(math.atan2(y - PAN_AXIS_XY[1], x - PAN_AXIS_XY[0])))
            out["cube_xy"].append([x, y])
            out["reset"].append(obs["pixels"])
            rng = np.random.default_rng(seed)
            keep_at = int(rng.integers(10, 40))  # a step of approach/descent, per seed
            seen = 0
            while seen < keep_at:
                obs, *_ = env.step(expert.select_action(obs))
                if expert.phase in ON_THE_WAY:
                    seen += 1
                elif seen:  # past the descent before the kept step
                    sys.exit(f"seed {seed}: the expert's approach took under {keep_at} steps")
            st = env.task_state()
            out["way"].append(obs["pixels"])
            out["offset"].append((st["cube_pos"] - st["tcp_pos"])[:2])
    finally:
        env.close()
    return {k: (v if k in ("reset", "way") else np.asarray(v)) for k, v in out.items()}


@torch.no_grad()
def features(pol: LeRobotPolicy, frames: list[dict[str, np.ndarray]],
             encoder: torch.nn.Module | None = None,
             cameras: tuple[str, ...] | None = None) -> np.ndarray:
    """The encoder's output for each frame, the cameras concatenated (as the U-Net gets them;
    all of the checkpoint's cameras unless `cameras` names some)."""
    from lerobot.envs.utils import preprocess_observation

    size = tuple(pol.info.image_size)
    enc = encoder if encoder is not None else pol.policy.diffusion.rgb_encoder
    rows = []
    for i in range(0, len(frames), 32):
        group = frames[i:i + 32]
        pixels = {c: resize_frames(np.stack([f[c] for f in group]), size).permute(0, 2, 3, 1)
                  .numpy() for c in pol.cameras}
        obs = preprocess_observation({"agent_pos": np.zeros((len(group), 6), np.float32),
                                      "pixels": pixels})
        obs["task"] = [""] * len(group)
        obs = pol.pre(obs)
        feats = [enc(obs[f"observation.images.{c}"]) for c in cameras or pol.cameras]
        rows.append(torch.cat(feats, dim=-1).float().numpy())
    return np.concatenate(rows)


class Keypoints(torch.nn.Module):
    """A Diffusion rgb_encoder cut before its linear layer: its own resize and eval crop, the
    backbone, then the SpatialSoftmax keypoints, flattened."""

    def __init__(self, encoder: torch.nn.Module) -> None:
        super().__init__()
        self.encoder = encoder

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        enc = self.encoder
        if enc.resize is not None:
            x = enc.resize(x)
        if enc.do_crop:
            x = enc.center_crop(x)
        return torch.flatten(enc.pool(enc.backbone(x)), start_dim=1)


def cv_errors(x: np.ndarray, y: np.ndarray, folds: int = 5, lam: float = 1e-2) -> np.ndarray:
    """Held-out |prediction - truth| (metres, Euclidean) per row, ridge on standardised x."""
    x = (x - x.mean(0)) / (x.std(0) + 1e-6)
    x = np.c_[x, np.ones(len(x))]
    err = np.empty(len(x))
    order = np.random.default_rng(0).permutation(len(x))
    for part in np.array_split(order, folds):
        train = np.setdiff1d(order, part)
        a = x[train]
        w = np.linalg.solve(a.T @ a + lam * len(train) * np.eye(a.shape[1]), a.T @ y[train])
        err[part] = np.linalg.norm(x[part] @ w - y[part], axis=1)
    return err


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", type=Path, help="Diffusion checkpoint folders")
    ap.add_argument("--task", default="pick_place_anywhere")
    ap.add_argument("--seeds", type=int, default=400)
    ap.add_argument("--seed-start", type=int, default=300_000,
                    help="first seed (default 300000: not the evaluation seeds)")
    ap.add_argument("--bins", type=int, default=4)
    ap.add_argument("--render", default="120x160", help="render size HxW, resized to the "
                    "checkpoint's input as eval does (default 120x160)")
    ap.add_argument("--random", action="store_true", help="add a randomly initialised encoder")
    ap.add_argument("--keypoints", action="store_true", help="also probe each encoder's "
                    "SpatialSoftmax keypoints (before its linear layer)")
    ap.add_argument("--per-camera", action="store_true", help="also probe each camera's "
                    "features alone")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    render = tuple(int(v) for v in args.render.split("x"))
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))

    names, encoders = [], []  # the checkpoints first: a wrong path fails before the renders
    for path in args.checkpoints:
        try:
            pol = LeRobotPolicy(path, batch_size=1, log=lambda s: None)
        except FileNotFoundError as exc:
            sys.exit(f"probe_cube: {exc}")
        if not pol.is_diffusion:
            sys.exit(f"{path}: a {pol.cfg.type} checkpoint; this probe reads a Diffusion "
                     "Policy's rgb_encoder, pass a diffusion checkpoint")
        name = path.parent.name if path.name == "pretrained_model" else path.name
        names.append(name)
        encoders.append((pol, None))
        if args.keypoints:
            names.append(f"{name}, keypoints")
            encoders.append((pol, Keypoints(pol.policy.diffusion.rgb_encoder).eval()))
    if args.random:
        pol = encoders[0][0]
        torch.manual_seed(0)
        fresh = type(pol.policy.diffusion.rgb_encoder)(pol.cfg).eval()
        names.append("random encoder")
        encoders.append((pol, fresh))

    data = collect(args.task, seeds, render)
    edges = np.quantile(data["bearing"], np.linspace(0, 1, args.bins + 1))
    bins = np.clip(np.searchsorted(edges, data["bearing"], side="right") - 1, 0, args.bins - 1)
    labels = [f"{edges[b]:.0f} to {edges[b + 1]:.0f}" for b in range(args.bins)]

    print(f"task {args.task}, {len(seeds)} seeds from {args.seed_start}, rendered "
          f"{args.render}; held-out error (mm), median / 90th percentile per bearing bin "
          "(deg, the robot's right first)")
    head = ["checkpoint", "probe", *labels, "all"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    probes = (("cube xy at reset", data["reset"], data["cube_xy"]),
              ("cube - tool xy, approaching", data["way"], data["offset"]))
    for name, (pol, enc) in zip(names, encoders, strict=True):
        views = [None] + ([(c,) for c in pol.cameras] if args.per_camera else [])
        for view in views:
            for probe, frames, target in probes:
                err = 1000 * cv_errors(features(pol, frames, enc, view), target)
                label = probe if view is None else f"{probe}, {view[0]} camera only"
                cells = [f"{np.median(err[bins == b]):.1f} / "
                         f"{np.quantile(err[bins == b], .9):.1f}" for b in range(args.bins)]
                print(f"| {name} | {label} | " + " | ".join(cells)
                      + f" | {np.median(err):.1f} / {np.quantile(err, .9):.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

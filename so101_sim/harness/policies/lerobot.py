"""A lerobot policy checkpoint as an ``EvalPolicy`` (diffusion first; ACT-like policies too).

Loading goes through lerobot's factory (``get_policy_class`` + ``from_pretrained``, and
``make_pre_post_processors(pretrained_path=...)`` for the saved normaliser pipelines), so any
lerobot policy whose observations match the env loads the way lerobot-eval loads it.
Observations take lerobot-eval's path: ``preprocess_observation`` (images to float CHW in
[0, 1], ``agent_pos`` to ``observation.state``), then the saved preprocessor.

Diffusion: the harness keeps the To-step observation history per env itself and calls
``predict_action_chunk`` with initial noise drawn from a ``torch.Generator`` seeded by the
episode seed, so the sampled chunk depends only on the episode. With DDIM (eta = 0) that noise
is the only randomness.

Batching: on CPU a row's result changes bitwise with the batch size (small-batch matmul kernels
differ) and, at some sizes, with its position in the batch. So every forward has exactly
``batch_size`` rows (padded with copies of the first), which a load-time check confirms is
position-independent; if it is not, each env gets its own forward.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# OpenMP: the harness keeps libgomp's default waits (spin briefly, then sleep):
# OMP_WAIT_POLICY=PASSIVE made a DDIM-10 forward of 8 rows 2.5x slower here (the U-Net's many
# small parallel regions each pay a futex wake-up). It runs forwards on half the cores
# (devices.eval_policy_threads: one thread on 2 cores), so a busy neighbour cannot stall a
# thread pool at its barriers (benchmarks/bench_busy.py).
import torch

from so101_sim.harness.camera_map import (
    describe_camera_map,
    resolve_camera_map,
    shown_camera_map,
)
from so101_sim.harness.policies.checks import (
    check_features,
    fingerprint,
    flag_names,
    weights_digest,
)
from so101_sim.harness.policies.encoder_split import use_split_encoder
from so101_sim.harness.policies.pooling import use_channels_last_pooling
from so101_sim.harness.policies.protocol import ChunkRequest, PolicyInfo
from so101_sim.harness.policies.traced import use_traced_unet
from so101_sim.tasks import ALL_CAMERAS as CAMERAS
from so101_sim.train.checkpoint import (
    check_files,
    checkpoint_name,
    demos_of,
    load_config,
    load_processors,
    load_weights,
    train_image_size,
)
from so101_sim.utils.devices import slow_bf16_note
from so101_sim.utils.heap import keep_freed_memory
from so101_sim.utils.trust import check_processor_files

#: The project's diffusion setting (DESIGN.md): To=2, Tp=16, Ta=8, DDIM with 10 steps.
STANDARD_DIFFUSION = {"n_obs_steps": 2, "horizon": 16, "n_action_steps": 8,
                      "noise_scheduler_type": "DDIM", "num_inference_steps": 10}
DEFAULT_BATCH = 8
#: Forward precision: fp32 (default), or bfloat16 autocast (see benchmarks/README.md for its
#: speed and outcome agreement on this CPU).
PRECISIONS = ("fp32", "bf16")


class _TakingTurns:
    """A processor pipeline that the two forward threads (harness.forwards) call in turn.

    lerobot's processor steps keep the transition they are working on in an attribute
    (``ProcessorStep._current_transition``), so two threads in one pipeline can swap
    observations: measured here, 51 of 2000 concurrent ACT forwards returned the other
    thread's actions. The pipelines cost little next to a forward, so they take turns.
    """

    def __init__(self, pipeline: Callable[[Any], Any]) -> None:
        self.pipeline = pipeline
        self._lock = threading.Lock()

    def __call__(self, data: Any) -> Any:
        with self._lock:
            return self.pipeline(data)


class LeRobotPolicy:
    """Loads a lerobot checkpoint directory and answers batched chunk requests.

    ``n_action_steps``, ``num_inference_steps`` and ``noise_scheduler`` (diffusion) and
    ``temporal_ensemble_coeff`` (ACT or diffusion) override the checkpoint's inference
    settings (with a warning); None keeps the checkpoint's.
    ``batch_size``: rows per forward (see the module docstring); 1 = one forward per env.
    ``camera_map``: policy camera name -> env camera, for checkpoints whose cameras are named
    after another rig (``so101_sim.harness.camera_map``). ``task_description`` goes into every
    batch as ``task``, as lerobot-eval passes it (language-conditioned policies read it).
    ACT with ``temporal_ensemble_coeff`` runs a forward every step, ensembled per env
    (``harness.policies.ensemble``).
    """

    #: predict_chunks may run on two driver threads at once (harness.forwards): its state is
    #: per slot, predict_action_chunk keeps none between calls, and the processors, which do
    #: keep the transition in flight, take turns (_TakingTurns).
    concurrent_forwards = True

    def __init__(self, path: str | Path, *, n_action_steps: int | None = None,
                 num_inference_steps: int | None = None, noise_scheduler: str | None = None,
                 temporal_ensemble_coeff: float | str | None = None,
                 batch_size: int = DEFAULT_BATCH, device: str = "cpu",
                 camera_map: dict[str, str] | None = None, task_description: str = "",
                 precision: str = "fp32", log: Callable[[str], None] = print) -> None:
        self.path = Path(path).expanduser()
        if precision not in PRECISIONS:
            raise ValueError(f"precision={precision!r} is invalid; expected one of "
                             f"{PRECISIONS} (bf16 = bfloat16 autocast of the forwards)")
        self.precision = precision
        self.task_text = task_description
        self.log = log
        note = slow_bf16_note(precision, device)
        if note:
            log(f"so101-sim eval: {note}")
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size} is invalid; expected >= 1")
        check_files(self.path)
        cfg = load_config(self.path)
        policy_cams, image_size, self.env_state = check_features(cfg, self.path)
        # policy camera name -> env camera that feeds it (--camera-map; identity by default)
        self.camera_map = resolve_camera_map(policy_cams, camera_map, f"checkpoint {self.path}")
        self.cameras = tuple(c for c in CAMERAS if c in self.camera_map.values())
        renamed = shown_camera_map(self.camera_map)  # renamed, or sharing one env camera
        asked = {"n_action_steps": n_action_steps, "num_inference_steps": num_inference_steps,
                 "noise_scheduler_type": noise_scheduler,
                 "temporal_ensemble_coeff": temporal_ensemble_coeff}
        self.is_diffusion = cfg.type == "diffusion"
        check_processor_files(self.path, cfg.type)  # before lerobot instantiates any step
        # asking for what the checkpoint already does is the same evaluation: same fingerprint
        saved = {k: getattr(cfg, k, None) for k in asked}
        self._apply_settings(cfg, {k: v for k, v in asked.items() if v is not None})
        asked = {k: None if v == saved[k] or (v == "off" and saved[k] is None) else v
                 for k, v in asked.items()}
        cfg.device = device
        self.cfg = cfg
        # These change speed, not results: utils/heap.py, pooling.py, traced.py,
        # encoder_split.py.
        keep_freed_memory(log)
        self.policy = load_weights(cfg, self.path)
        use_channels_last_pooling(self.policy)
        use_traced_unet(self.policy, log)
        use_split_encoder(self.policy)
        self.pre, self.post = (_TakingTurns(p) for p in load_processors(cfg, self.path, device))
        self.batch_size = batch_size
        self._gens: dict[int, torch.Generator] = {}
        if batch_size > 1 and not self._batching_is_row_independent():
            log(f"so101-sim eval: note: a row's actions depend on its position in a "
                f"{batch_size}-row batch on this machine; running one forward per env so "
                "results stay independent of --n-envs")
            self.batch_size = 1
        self.info = PolicyInfo(
            name=checkpoint_name(self.path),
            cameras=self.cameras, needs_env_state=self.env_state, image_size=image_size,
            train_image_size=train_image_size(self.path),
            n_obs_steps=self.n_obs_steps, n_action_steps=self.n_action_steps,
            fingerprint=fingerprint(self.path, {**asked, "batch_size": self.batch_size,
                                                 **({"precision": precision}
                                                    if precision != "fp32" else {}),
                                                 **({"camera_map": renamed} if renamed else {})}),
            weights=weights_digest(self.path / "model.safetensors"),
            details=self._details(), camera_map=renamed, demos=demos_of(self.path))

    # --------------------------------------------------------------------- settings
    def _apply_settings(self, cfg: Any, asked: dict[str, Any]) -> None:
        """Check what the user asked for against the checkpoint; refuse what cannot change."""
        n_obs = int(getattr(cfg, "n_obs_steps", 1))
        if self.is_diffusion:
            limit = cfg.horizon - n_obs + 1
            if "n_action_steps" in asked and not 1 <= asked["n_action_steps"] <= limit:
                raise ValueError(f"n_action_steps={asked['n_action_steps']} is invalid for "
                                 f"{self.path}: horizon {cfg.horizon} and n_obs_steps {n_obs} "
                                 f"allow 1..{limit}")
            steps = asked.get("num_inference_steps")
            if steps is not None and not 1 <= steps <= cfg.num_train_timesteps:
                raise ValueError(f"num_inference_steps={steps} is invalid; expected "
                                 f"1..{cfg.num_train_timesteps} (num_train_timesteps)")
            if asked.get("noise_scheduler_type", "DDIM") not in ("DDIM", "DDPM"):
                raise ValueError(f"noise_scheduler={asked['noise_scheduler_type']!r} is invalid; "
                                 "expected 'DDIM' or 'DDPM'")
            self._ensemble_settings(asked, None)
            if asked.get("temporal_ensemble_coeff") is not None:
                del asked["n_action_steps"]  # every action of each chunk is read: below
        else:
            other = sorted(set(asked) - {"n_action_steps", "temporal_ensemble_coeff"})
            if other:
                raise ValueError(f"{flag_names(other)} appl{'y' if len(other) > 1 else 'ies'}"
                                 f" to diffusion policies; {self.path} is a {cfg.type!r} "
                                 f"policy: drop {'them' if len(other) > 1 else 'it'}")
            for key in ("n_action_steps", "temporal_ensemble_coeff"):
                if key in asked and not hasattr(cfg, key):
                    raise ValueError(f"{cfg.type!r} policies have no {key} to override "
                                     f"({flag_names([key])}): drop it")
            self._ensemble_settings(asked, getattr(cfg, "temporal_ensemble_coeff", None))
        for key, value in asked.items():
            if getattr(cfg, key, None) != value:  # DiffusionConfig has no ensembling field
                self.log(f"so101-sim eval: warning: checkpoint {self.path} says "
                         f"{key}={getattr(cfg, key, None)!r}; using {value!r} as asked")
                setattr(cfg, key, value)
        coeff = getattr(cfg, "temporal_ensemble_coeff", None)
        chunk = getattr(cfg, "chunk_size", None)
        if self.is_diffusion:
            have = {k: getattr(cfg, k) for k in STANDARD_DIFFUSION}
            if coeff is not None:  # the chunk from the current step on: horizon - To + 1
                chunk = cfg.n_action_steps = cfg.horizon - n_obs + 1
                have["n_action_steps"] = "1, temporally ensembled"
            if have["num_inference_steps"] is None:
                have["num_inference_steps"] = cfg.num_train_timesteps
            off = {k: v for k, v in have.items() if v != STANDARD_DIFFUSION[k]}
            if off:
                self.log(f"so101-sim eval: warning: {self.path} evaluates with {off}, not the "
                         f"project's standard {STANDARD_DIFFUSION} (change what inference "
                         "allows with --n-action-steps, --inference-steps, --noise-scheduler)")
            if cfg.noise_scheduler_type == "DDPM":
                self.log("so101-sim eval: warning: DDPM sampling draws noise inside every step "
                         "from torch's global generator, so an episode's actions also depend on "
                         "which envs share its batch; use --noise-scheduler DDIM for "
                         "per-seed results")
        elif n_obs != 1:
            raise ValueError(f"{cfg.type!r} policy with n_obs_steps={n_obs} is not supported: "
                             "the harness feeds observation histories to diffusion policies only")
        self.ensemble = None
        if coeff is not None:  # a forward every step, averaged over the chunks so far
            from so101_sim.harness.policies.ensemble import SlotEnsemblers

            self.ensemble = SlotEnsemblers(coeff, chunk)
        self.n_obs_steps = n_obs
        self.n_action_steps = 1 if coeff is not None else int(getattr(cfg, "n_action_steps", 1))

    def _ensemble_settings(self, asked: dict[str, Any], saved: float | None) -> None:
        """Temporal ensembling executes one action per forward, as lerobot's ACTConfig requires."""
        coeff = asked.get("temporal_ensemble_coeff")
        if coeff == "off":  # chunk-wise: --n-action-steps (default the checkpoint's) per forward
            asked["temporal_ensemble_coeff"] = None
            return
        if coeff is None:
            if saved is not None and asked.get("n_action_steps", 1) != 1:
                raise ValueError(f"--n-action-steps {asked['n_action_steps']}: {self.path} "
                                 f"ensembles temporally (temporal_ensemble_coeff={saved}), one "
                                 "action per forward; add --temporal-ensemble off to run it "
                                 "chunk-wise")
            return
        if isinstance(coeff, str) or not np.isfinite(coeff):
            raise ValueError(f"--temporal-ensemble {coeff} is invalid; expected a finite "
                             "coefficient (0.01 in ACT's paper) or 'off'")
        if asked.get("n_action_steps", 1) != 1:
            raise ValueError(f"--n-action-steps {asked['n_action_steps']} with "
                             "--temporal-ensemble: ensembling executes one action per forward; "
                             "drop --n-action-steps")
        asked["n_action_steps"] = 1

    def _details(self) -> dict[str, str]:
        cfg = self.cfg
        d = {"policy type": cfg.type, "checkpoint": str(self.path)}
        if self.is_diffusion:
            steps = cfg.num_inference_steps or cfg.num_train_timesteps
            d["To / Tp / Ta"] = f"{cfg.n_obs_steps} / {cfg.horizon} / {cfg.n_action_steps}"
            d["sampler"] = f"{cfg.noise_scheduler_type}-{steps}, noise seeded per episode"
        else:
            d["observations / chunk executed"] = f"{self.n_obs_steps} / {self.n_action_steps}"
        if self.ensemble is not None:
            d["temporal ensembling"] = (f"coefficient {cfg.temporal_ensemble_coeff} over "
                                        f"{self.ensemble.chunk_size}-action chunks, a forward "
                                        "every step")
        if any(p != e for p, e in self.camera_map.items()):
            d["cameras"] = describe_camera_map(self.camera_map)
        d["batched inference"] = (f"padded to {self.batch_size} rows per forward"
                                  if self.batch_size > 1 else "one env per forward")
        if self.precision != "fp32":
            d["precision"] = "bf16 autocast"
        return d

    # --------------------------------------------------------------------- EvalPolicy
    def start_episode(self, slot: int, seed: int) -> None:
        self._gens[slot] = torch.Generator().manual_seed(int(seed))
        if self.ensemble is not None:
            self.ensemble.start(slot)

    def predict_chunks(self, requests: Sequence[ChunkRequest]) -> np.ndarray:
        out = []
        for start in range(0, len(requests), self.batch_size):
            group = list(requests[start:start + self.batch_size])
            pad = self.batch_size - len(group)
            rows = group + [group[0]] * pad
            batch = self._observation_batch(rows)
            noise = None
            if self.is_diffusion:
                drawn = [self._draw_noise(r.slot) for r in group]
                noise = torch.stack(drawn + [drawn[0]] * pad)
            if self.ensemble is not None:
                chunks = self._predict_raw(batch, noise)[:len(group)]
                actions = self.post(self.ensemble.step([r.slot for r in group], chunks))
                actions = actions.to("cpu", torch.float32)
            else:
                actions = self._predict(batch, noise)
            out.append(actions[:len(group)].numpy().astype(np.float32))
        return np.concatenate(out)

    def _draw_noise(self, slot: int) -> torch.Tensor:
        horizon = self.cfg.horizon
        dim = self.cfg.output_features["action"].shape[0]
        return torch.randn((horizon, dim), generator=self._gens[slot], dtype=torch.float32)

    def _observation_batch(self, rows: Sequence[ChunkRequest]) -> dict[str, torch.Tensor]:
        """Preprocessed inputs: (B, To, ...) for diffusion, (B, ...) otherwise."""
        from lerobot.envs.utils import preprocess_observation

        steps = []
        for t in range(self.n_obs_steps):
            obs = [r.history[t] for r in rows]
            env_batch: dict[str, Any] = {"agent_pos": np.stack([o["agent_pos"] for o in obs])}
            if self.cameras:
                env_batch["pixels"] = {p: np.stack([o["pixels"][e] for o in obs])
                                       for p, e in self.camera_map.items()}
            if self.env_state:
                env_batch["environment_state"] = np.stack(
                    [o["environment_state"] for o in obs])
            obs = preprocess_observation(env_batch)
            obs["task"] = [self.task_text] * len(rows)  # as lerobot-eval passes it
            steps.append(self.pre(obs))
        keys = [k for k in self.cfg.input_features if k in steps[0]]
        if not self.is_diffusion:
            batch = {k: steps[0][k] for k in keys}
            if "task" in steps[0]:
                batch["task"] = steps[0]["task"]
            return batch
        return {k: torch.stack([s[k] for s in steps], dim=1) for k in keys}

    @torch.no_grad()
    def _predict_raw(self, batch: dict[str, Any], noise: torch.Tensor | None) -> torch.Tensor:
        """The policy's whole chunk, normalised (before the postprocessor)."""
        device_type = torch.device(self.cfg.device).type
        with torch.autocast(device_type, dtype=torch.bfloat16,
                            enabled=self.precision == "bf16"):
            if self.is_diffusion:
                noise = None if noise is None else noise.to(self.cfg.device)
                chunk = self.policy.predict_action_chunk(batch, noise=noise)
            else:
                chunk = self.policy.predict_action_chunk(batch)
        return chunk.float()

    @torch.no_grad()
    def _predict(self, batch: dict[str, Any], noise: torch.Tensor | None) -> torch.Tensor:
        actions = self._predict_raw(batch, noise)
        if not self.is_diffusion:
            actions = actions[:, :self.n_action_steps]
        return self.post(actions).to("cpu", torch.float32)

    def _batching_is_row_independent(self) -> bool:
        """Do rows come out bitwise the same whatever their position and batch mates?"""
        gen = torch.Generator().manual_seed(0)
        batch: dict[str, Any] = {}
        lead = (self.batch_size, self.n_obs_steps) if self.is_diffusion else (self.batch_size,)
        for key, ft in self.cfg.input_features.items():
            batch[key] = torch.rand((*lead, *ft.shape), generator=gen).to(self.cfg.device)
        noise = None
        if not self.is_diffusion:
            batch["task"] = [self.task_text] * self.batch_size
        if self.is_diffusion:
            noise = torch.randn((self.batch_size, self.cfg.horizon,
                                 self.cfg.output_features["action"].shape[0]), generator=gen)
        # Ensembling reads every action of the chunk, not only the executed ones.
        predict = self._predict if self.ensemble is None else self._predict_raw
        first = predict(batch, noise)
        order = torch.roll(torch.arange(self.batch_size), 1)
        second = predict({k: v if k == "task" else v[order] for k, v in batch.items()},
                         None if noise is None else noise[order])
        return torch.equal(first[order], second)


# ------------------------------------------------------------------------ loading helpers

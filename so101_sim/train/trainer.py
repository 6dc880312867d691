"""Train a lerobot policy (DiffusionPolicy; ACT) on a recorded LeRobotDataset, fast on CPU, with
EMA weights.

What differs from `lerobot-train`: frames are decoded and resized once into memory
(`frame_cache`), batches are gathered by array indexing with lerobot's padding rules, an EMA copy
of the weights is kept (diffusers' `EMAModel`, the seed's power 0.75 / max 0.9999) for evaluation,
`--resume` restores every RNG (a resumed run is the same run), a preset's [augment] jitters frames.

Run layout under `out/`:
    checkpoints/step_NNNNNNN/pretrained_model/   EMA weights in lerobot's format (+ processors)
    checkpoints/step_NNNNNNN/training_state.pt   raw weights, optimiser, scheduler, EMA, RNGs
                                                 (tensors and plain values only: it loads
                                                 with torch.load(weights_only=True), so a
                                                 crafted file cannot run code on --resume)
    pretrained_model/                            the final EMA policy
    train_log.jsonl                              step, loss, lr, samples/s, EMA decay
    frame_cache/                                 decoded frames (.npy), deleted at the last step
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

# OpenMP waits stay libgomp's default (spin briefly, then sleep): OMP_WAIT_POLICY=PASSIVE made a
# cpu-preset step 1.2x slower on an idle machine. Next to a busy process, AdaptiveThreads stops
# the pool from waiting on a thread that lost its core.
import torch
from tqdm import tqdm

from so101_sim.dataset import recorded_seeds, recorded_task
from so101_sim.dataset.reader import NotADatasetError, open_lerobot_dataset
from so101_sim.train.augment import FrameAugmenter
from so101_sim.train.checkpoint import demos_info, eval_seeds_note, init_weights_from
from so101_sim.train.demos import (
    CloseWeighting,
    demos_notes,
    gather_batch,
    load_demos,
    normalization_stats,
    sample_weights,
)
from so101_sim.train.frame_cache import drop_cache
from so101_sim.train.presets import load_preset, make_config, policy_features
from so101_sim.train.state import (
    TrainError,
    TrainingStopped,
    architecture,
    check_counts,
    check_same_architecture,
    check_same_dataset,
    copy_policy,
    discard_partial_checkpoint,
    joined_setups,
    list_checkpoints,
    load_training_state,
    own_info,
    resumed_sizes,
    save_ema_policy,
    truncate_log,
)
from so101_sim.train.threads import AdaptiveThreads, BatchParts
from so101_sim.utils.devices import resolve_device, resolve_precision, slow_bf16_note, threads_note
from so101_sim.utils.locks import hold_folder, lock_scope
from so101_sim.utils.paths import foreign_folder
from so101_sim.utils.versions import run_setup

#: Training precision: fp32, or bf16 autocast (AMX/AVX512-BF16 CPUs: 1.45x faster per step;
#: slower on an H200); weights, optimiser and EMA stay fp32. "auto": see devices.py.
PRECISIONS = ("auto", "fp32", "bf16")


# ----------------------------------------------------------------------------- run


@dataclass
class TrainResult:
    out: Path
    step: int
    final_loss: float
    wall_s: float
    samples_per_s: float
    pretrained_dir: Path


@lock_scope  # releases the run folder's lock (hold_folder below)
def train(dataset_dir: Path, out: Path, preset_name: str = "cpu", steps: int | None = None,
          batch_size: int | None = None, resume: bool = False, keep_checkpoints: int = 3,
          progress: bool = True, log_every: int | None = None,
          precision: str = "fp32", device: str = "cpu",
          threads: int | None = None, stop_at: int | None = None,
          init_from: Path | None = None, keep_frame_cache: bool = False,
          oversample_closes: float | None = None) -> TrainResult:
    """Train `preset_name` on the dataset at `dataset_dir`; see the module docstring.

    `device` is auto|cpu|cuda|mps (`devices.resolve_device`); `precision` fp32|bf16|auto.
    `threads`: torch CPU threads, fixed; None on the CPU: fitted to the cores other
    processes leave (`train.threads.AdaptiveThreads`), so a busy neighbour does not stall
    the thread pool.
    `stop_at`: save and return at this step while the schedule stays sized for `steps`, so a
    short run is the prefix of the long one (`resume=True` later continues it exactly).
    `init_from`: a checkpoint folder whose weights a new run starts from (fine-tuning).
    `keep_frame_cache`: keep `frame_cache/` when the run reaches `steps` (default: delete it).
    `oversample_closes`: draw frames near each close of the gripper this many times as often
    (`demos.CloseWeighting`); None draws every frame alike. A resumed run keeps its own.
    """
    from diffusers.optimization import get_scheduler
    from diffusers.training_utils import EMAModel
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    preset = load_preset(preset_name)
    ts = preset.train
    log_every = int(log_every or ts.log_every)
    if precision not in PRECISIONS:
        raise TrainError(f"precision={precision!r} is invalid; expected one of {PRECISIONS}")
    try:
        device = resolve_device(device)
    except ValueError as e:
        raise TrainError(str(e)) from None
    precision = resolve_precision(precision, device)
    note = slow_bf16_note(precision, device)
    if note:
        print(f"so101-sim train: {note}")
    check_counts(steps=steps, batch_size=batch_size, threads=threads, stop_at=stop_at)
    weighting = None if oversample_closes is None else CloseWeighting(float(oversample_closes))
    out = Path(out)
    existed = out.exists()
    hold_folder(out, "the training run",  # one writer: a second run is refused here
                again=lambda: "resume" if list_checkpoints(out) else "rerun")
    if (what := foreign_folder(out)) is not None:  # e.g. --out the --dataset folder
        raise TrainError(f"--out {out} {what}; a run writes its checkpoints and frame cache "
                         "there, among its files; choose another --out")
    existing = list_checkpoints(out)
    if existing and not resume:
        raise TrainError(f"{out} already holds checkpoints (last {existing[-1].name}); pass "
                         "--resume to continue that run or choose another --out")
    if resume and not existing:
        what = "does not exist" if not existed else "holds no checkpoint with a training_state.pt"
        raise TrainError(f"--resume: {out} {what}, so there is nothing to continue; check --out, "
                         "or start a new run without --resume")
    if resume:
        steps, batch_size = resumed_sizes(existing[-1], steps, batch_size, out)
    steps = int(steps if steps is not None else ts.steps)
    batch_size = int(batch_size if batch_size is not None else ts.batch_size)
    if stop_at is not None and not 1 <= stop_at <= steps:
        raise TrainError(f"--stop-at {stop_at} is outside 1..--steps ({steps}); give the step "
                         "to pause at, at most the run's total steps")
    end = steps if stop_at is None else stop_at
    if resume and init_from is not None:
        raise TrainError(f"--init-from starts a new run from a checkpoint's weights and --resume "
                         f"continues {out} from its own: drop one of them")
    try:
        dataset = open_lerobot_dataset(dataset_dir)
    except NotADatasetError as exc:
        raise TrainError(str(exc)) from None
    missing = [k for k in ("observation.state", "action") if k not in dataset.meta.features]
    if missing:
        raise TrainError(f"dataset {dataset_dir} lacks {missing}; expected a so101-sim recording")
    cams = tuple(k.split(".")[-1] for k in dataset.meta.video_keys)
    torch.manual_seed(ts.seed)
    rng = np.random.default_rng(ts.seed)
    cfg = make_config(preset, *policy_features(preset.image_size, cams,
                                               dataset.meta.features["action"]["shape"][0]))
    cfg.device = device
    policy = get_policy_class(cfg.type)(cfg)
    started_from = None  # a fine-tuning run's starting checkpoint (recorded in every sidecar)
    if init_from is not None:
        try:
            started_from = init_weights_from(policy, init_from)
        except (FileNotFoundError, ValueError) as e:
            raise TrainError(f"--init-from: {e}") from None
    policy.to(device).train()
    pre, post = make_pre_post_processors(cfg, dataset_stats=normalization_stats(dataset, preset))
    # lerobot's AdamW settings for the policy type (ACT: a parameter group for the backbone);
    # clipping only where the preset asks (grad_clip_norm > 0), as the diffusion runs had none.
    opt = cfg.get_optimizer_preset()
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=opt.lr, betas=opt.betas,
                                  eps=opt.eps, weight_decay=opt.weight_decay)
    # Diffusion: its cosine with warm-up; ACT has no schedule in lerobot: a constant lr.
    scheduler = get_scheduler(getattr(cfg, "scheduler_name", "constant"), optimizer=optimizer,
                              num_warmup_steps=getattr(cfg, "scheduler_warmup_steps", 0),
                              num_training_steps=steps)
    ema = EMAModel(policy.parameters(), decay=ts.ema_max_decay, min_decay=ts.ema_min_decay,
                   update_after_step=ts.ema_update_after_step, use_ema_warmup=True,
                   inv_gamma=ts.ema_inv_gamma, power=ts.ema_power)
    step, wall_before = 0, 0.0
    precision_history = [[0, precision]]  # [first step, precision] per stretch of the run
    setup = run_setup()  # software and CPU: a resume on others is not bitwise this run
    setup_history, _ = joined_setups(None, 0, setup)  # and [first step, setup]
    log_path = out / "train_log.jsonl"
    if existing and resume:
        state = load_training_state(existing[-1] / "training_state.pt", device)
        if state["preset"] != preset.name or state["dataset"] != str(Path(dataset_dir).resolve()):
            raise TrainError(f"{out} was trained with preset {state['preset']!r} on "
                             f"{state['dataset']}; resume it with the same --preset and --dataset")
        check_same_architecture(state, preset, out)
        check_same_dataset(existing[-1], dataset, dataset_dir, out)
        if state.get("oversample_closes") != oversample_closes:
            raise TrainError(f"{out} was trained with --oversample-closes "
                             f"{state.get('oversample_closes')}, not {oversample_closes}; "
                             "resume it with the same value (leave the flag out for None)")
        try:
            policy.load_state_dict(state["model"])
        except RuntimeError as e:
            raise TrainError(f"{out}: the checkpoint's weights do not fit preset "
                             f"{preset.name!r} as it is now ({str(e).splitlines()[0]}); the "
                             "preset file changed since the run started: resume with the "
                             "preset file the run was started with") from None
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        ema.load_state_dict(state["ema"])
        torch.set_rng_state(state["torch_rng"].cpu())
        if device == "cuda" and "cuda_rng" in state:
            torch.cuda.set_rng_state(state["cuda_rng"].cpu())
        rng.bit_generator.state = state["numpy_rng"]
        step, wall_before = state["step"], state["wall_s"]
        started_from = state.get("init_from")
        history = state.get("precision_history", [[0, state.get("precision", "fp32")]])
        if history[-1][1] != precision:
            print(f"so101-sim train: precision changed {history[-1][1]} -> {precision} at step "
                  f"{step}; so101_sim_train.json and the model card record both")
            history = [*history, [step, precision]]
        precision_history = history
        setup_history, differ = joined_setups(state.get("setup_history"), step, setup)
        if differ:
            print(f"so101-sim train: resuming at step {step} on another setup "
                  f"({'; '.join(differ)}, then vs now): the steps from here are not bitwise "
                  "those of an uninterrupted run; so101_sim_train.json records both")
        if state["steps"] != steps:
            print(f"so101-sim train: total steps changed {state['steps']} -> {steps}; the cosine "
                  "schedule is stretched from here on")
        truncate_log(log_path, step)
        if stop_at is not None and step >= stop_at:
            raise TrainError(f"--stop-at {end}: {out} is already at step {step}; give a later "
                             "--stop-at, or leave it out to train to --steps")
        if step >= steps:  # finished: a kill-safe loop may run the same command again
            print(f"so101-sim train: {out} is already at step {step} of {steps}; nothing to "
                  "train")
            return finished_run(out, existing[-1], step, state["wall_s"], keep_frame_cache)
    start_step = step
    out.mkdir(parents=True, exist_ok=True)
    info = {"preset": preset.name, "preset_file": str(preset.path), "dataset": str(dataset_dir),
            "dataset_episodes": dataset.meta.total_episodes,
            "dataset_frames": dataset.meta.total_frames,
            **demos_info(recorded_task(dataset_dir), dataset.meta.tasks.index,
                         recorded_seeds(dataset_dir)),
            "dataset_image_size": list(dataset.meta.features[dataset.meta.video_keys[0]]
                                       ["shape"][:2]),
            "policy_image_size": list(preset.image_size),
            "image_pipeline": "so101_sim.utils.image_pipeline.resize_frames (bilinear, antialias)",
            "policy_type": cfg.type, "weights": "EMA", "init_from": started_from,
            "augment": preset.augment, "oversample_closes": weighting and asdict(weighting),
            "batch_size": batch_size, "precision": precision,
            "precision_history": precision_history, "setup_history": setup_history,
            "total_steps": steps, "device": device,
            "train_settings": asdict(ts)}

    for note in filter(None, (eval_seeds_note(dataset_dir, info),
                              *demos_notes(dataset_dir, dataset, preset))):
        print(note)  # before the frames decode, which can take minutes
    demos = load_demos(dataset, preset, out / "frame_cache")
    probs = sample_weights(demos, dataset.meta.features["action"]["names"], weighting)
    if probs is not None:
        near = probs > probs.min()
        print(f"so101-sim train: {near.mean():.0%} of the frames are near a gripper close; drawn "
              f"{weighting.factor:g}x as often, they are {probs[near].sum():.0%} of each batch")
    stop = {"signal": None}

    def on_signal(signum: int, _frame: object) -> None:
        stop["signal"] = signum

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    obs_offsets, act_offsets = cfg.observation_delta_indices, cfg.action_delta_indices

    def save(at_step: int, wall: float, loss: float) -> Path:
        ck = out / "checkpoints" / f"step_{at_step:07d}"
        ck.mkdir(parents=True, exist_ok=True)
        meta = {**info, "step": at_step, "train_wall_s": round(wall, 1), "last_loss": loss}
        try:
            save_ema_policy(policy, ema, pre, post, ck / "pretrained_model", meta)
            torch.save({"model": policy.state_dict(), "optimizer": optimizer.state_dict(),
                        "scheduler": scheduler.state_dict(), "ema": ema.state_dict(),
                        "torch_rng": torch.get_rng_state(),
                        "numpy_rng": rng.bit_generator.state,
                        **({"cuda_rng": torch.cuda.get_rng_state()} if device == "cuda"
                           else {}),
                        "step": at_step, "steps": steps, "wall_s": wall,
                        "preset": preset.name, "precision_history": precision_history,
                        "setup_history": setup_history,
                        "init_from": started_from, "oversample_closes": oversample_closes,
                        "preset_arch": architecture(preset),
                        "dataset": str(Path(dataset_dir).resolve())}, ck / "training_state.tmp")
        except BaseException:
            discard_partial_checkpoint(ck)  # the previous checkpoint stays the last one
            raise
        (ck / "training_state.tmp").replace(ck / "training_state.pt")
        for old_ck in list_checkpoints(out)[:-keep_checkpoints]:
            (old_ck / "training_state.pt").unlink()  # keep its EMA policy, drop the bulk
        return ck

    if threads:
        torch.set_num_threads(threads)
        if device == "cpu" and (note := threads_note(threads, "train")):
            print(note)
    tuner = AdaptiveThreads() if device == "cpu" and not threads else None
    run_parts, augment = BatchParts(), FrameAugmenter(preset.augment) if preset.augment else dict

    def batch_loss(part: dict) -> torch.Tensor:
        with torch.autocast(device, dtype=torch.bfloat16, enabled=precision == "bf16"):
            return policy.forward(part)[0]

    desc = f"train {preset.name}" + (f" (to {end} of {steps})" if end < steps else "")
    bar = tqdm(total=end, initial=step, desc=desc, unit="step",
               disable=not progress, dynamic_ncols=True)
    t0, loss_val, window = time.perf_counter(), math.nan, []
    log = log_path.open("a")
    try:
        while step < end and stop["signal"] is None:
            t_step = time.perf_counter()
            idx = rng.choice(demos.starts, size=batch_size, p=probs)
            batch = pre(augment(gather_batch(demos, idx, obs_offsets, act_offsets)))
            optimizer.zero_grad(set_to_none=True)
            loss_val = run_parts(batch_loss, batch, tuner.parts if tuner else 1)
            if ts.grad_clip_norm > 0:
                torch.nn.utils.clip_grad_norm_(policy.parameters(), ts.grad_clip_norm)
            optimizer.step()
            scheduler.step()
            ema.step(policy.parameters())
            step += 1
            window.append((loss_val, time.perf_counter() - t_step))
            if tuner is not None:
                tuner.after_step(step, window[-1][1])
            if step % log_every == 0 or step == end:
                mean_loss = float(np.mean([w[0] for w in window]))
                sps = batch_size * len(window) / sum(w[1] for w in window)
                log.write(json.dumps({"step": step, "loss": round(mean_loss, 6),
                                      "lr": scheduler.get_last_lr()[0],
                                      "samples_per_s": round(sps, 2),
                                      "threads": torch.get_num_threads(),
                                      "parts": tuner.parts if tuner else 1,
                                      "ema_decay": round(ema.cur_decay_value or 0.0, 6),
                                      "wall_s": round(wall_before + time.perf_counter() - t0, 1)})
                          + "\n")
                log.flush()
                os.fsync(log.fileno())  # whole lines on disk; a torn one is dropped on resume
                bar.set_postfix(loss=f"{mean_loss:.4f}", samples_s=f"{sps:.1f}")
                window.clear()
            bar.update(1)
            if step % ts.checkpoint_every == 0 and step < end:
                save(step, wall_before + time.perf_counter() - t0, loss_val)
        wall = wall_before + time.perf_counter() - t0
        ck = save(step, wall, loss_val)
    finally:
        run_parts.close()
        bar.close()
        log.close()
        for s, h in old.items():
            signal.signal(s, h)
    if stop["signal"] is not None:
        raise TrainingStopped(f"stopped by signal {stop['signal']} at step {step}; "
                                f"checkpoint {ck}")
    final = ck / "pretrained_model"
    if step == steps:  # the run's own policy; a pause at --stop-at leaves only its checkpoint
        final = finish(out, ck, keep_frame_cache)
    run_s = time.perf_counter() - t0
    return TrainResult(out=out, step=step, final_loss=loss_val, wall_s=wall,
                       samples_per_s=(step - start_step) * batch_size / max(run_s, 1e-9),
                       pretrained_dir=final)


def finish(out: Path, ck: Path, keep_frame_cache: bool) -> Path:
    """The last checkpoint's policy as the run's own, and the frame cache gone."""
    final = out / "pretrained_model"
    copy_policy(ck / "pretrained_model", final)
    if not keep_frame_cache:
        drop_cache(out / "frame_cache")
    return final


def finished_run(out: Path, ck: Path, step: int, wall: float,
                 keep_frame_cache: bool) -> TrainResult:
    """A finished run resumed: nothing trained or saved again (its checkpoint keeps its last
    loss), the final policy put in place if a kill came between the two."""
    final = out / "pretrained_model"
    if not (final / "model.safetensors").is_file():
        final = finish(out, ck, keep_frame_cache)
    loss = own_info(ck).get("last_loss", math.nan)
    return TrainResult(out=out, step=step, final_loss=loss, wall_s=wall, samples_per_s=0.0,
                       pretrained_dir=final)



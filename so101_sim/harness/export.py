"""Ship a trained policy: fp16 weights (lerobot restores fp32 on load) plus a model card.

The card's numbers come from files, not from the person writing it: the training facts from the
checkpoint's `so101_sim_train.json`, the training curve from the run's `train_log.jsonl`, and the
success rate from a harness run's `eval_info.json`. A multi-task checkpoint gets one eval per
task (`--eval` repeated, or one `--task all` suite folder), stored as `eval_info_<task>.json`
(``recorded_eval``) and shown as one row per task.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from shlex import quote

from so101_sim.harness.curve import plot_curve, read_curve, widest_rows
from so101_sim.harness.policies.checks import ACT_TRAINING_ONLY, weights_digest
from so101_sim.harness.results import INFO, check_eval_info
from so101_sim.harness.trained_on import check_unseen_seeds
from so101_sim.tasks import DEFAULT_TASK, TaskSpecError, load_task
from so101_sim.train.checkpoint import (
    TRAIN_INFO,
    checkpoint_name,
    damaged,
    demos_of,
    nearby_policies,
    other_kind,
    ranges_text,
)
from so101_sim.utils.locks import folder_lock
from so101_sim.utils.text import md_row
from so101_sim.utils.trust import check_processor_files


def _fp16_copy(src: Path, dst: Path, drop: str | None = None) -> int:
    """Store `src` in fp16 at `dst`, leaving out tensors whose name starts with `drop`; returns
    the number of parameters left out."""
    from safetensors.torch import load_file, save_file

    state = load_file(src)
    gone = {k for k in state if drop and k.startswith(drop)}
    save_file({k: v.half() if v.is_floating_point() else v for k, v in state.items()
               if k not in gone}, dst,
              metadata={"format": "pt", "so101_sim": "stored fp16; loads into fp32"})
    return sum(state[k].numel() for k in gone)


def _drop_act_vae(folder: Path) -> bool:
    """Turn an ACT checkpoint's config to `use_vae: false` (the shipped copy keeps no VAE
    encoder); True when it was an ACT trained with one."""
    path = folder / "config.json"
    cfg = json.loads(path.read_text())
    if cfg.get("type") != "act" or not cfg.get("use_vae"):
        return False
    cfg["use_vae"] = False
    path.write_text(json.dumps(cfg, indent=4) + "\n")
    return True


def loss_curve(log: Path, points: int = 8) -> list[dict]:
    rows = []
    for n, line in enumerate(log.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            if line.strip():
                print(f"so101-sim export: {log}: skipped unreadable line {n}")
    if not rows:
        return []
    pick = sorted({round(i * (len(rows) - 1) / (points - 1)) for i in range(points)})
    return [rows[i] for i in pick]


def _precision(train_info: dict) -> str:
    """'fp32', or which steps ran in which precision when a resume changed it."""
    hist = train_info.get("precision_history") or [[0, train_info.get("precision", "fp32")]]
    names = {"fp32": "fp32", "bf16": "bf16 autocast"}
    if len(hist) == 1:
        return names.get(hist[0][1], hist[0][1])
    ends = [h[0] for h in hist[1:]] + [train_info["step"]]
    return "; ".join(f"{names.get(p, p)} steps {a}-{b}" for (a, p), b in zip(hist, ends,
                                                                             strict=True))


def _eval_rows(eval_info: dict, label: str) -> list[str]:
    agg, cfg = eval_info["aggregated"], eval_info["config"]
    lo, hi = agg["success_ci95"]
    modes = ", ".join(f"{k} {v}" for k, v in sorted(agg.get("failure_modes", {}).items()))
    return [md_row(label, f"**{agg['pc_success']:.1f}%** (95% Wilson [{lo:.1f}, {hi:.1f}]) on "
                   f"{agg['n_episodes']} evaluation seeds from {cfg['seed_start']}; outcomes: "
                   f"{modes or 'n/a'}; images: {cfg.get('images', 'n/a')}")]


def _recording_note(dataset: str) -> str:
    """How the demos were recorded (DART noise, expert options), from the dataset sidecar."""
    side = Path(dataset).expanduser() / "so101_sim_recording.json"
    if not side.is_file():
        return ""
    s = json.loads(side.read_text())
    parts = [f"DART noise {s['dart_noise']:g}" if s.get("dart_noise") else "no DART noise"]
    expert = s.get("expert") or {}
    if expert.get("recover"):
        parts.append("recovering expert (retries)")
    if "clearance" in expert:
        parts.append(f"grasp clearance {expert['clearance']:g} m")
    return "; " + ", ".join(parts)


def _success_rows(rows: list[dict]) -> list[str]:
    tasks = sorted({r.get("task", DEFAULT_TASK) for r in rows})
    n = " or ".join(str(k) for k in sorted({r["episodes"] for r in rows}))
    lines = ["", "Closed-loop success along training (`so101-sim curve`, each checkpoint on "
             f"the same {n} evaluation seeds from {rows[-1]['seed_start']}"
             + (", per task" if len(tasks) > 1 else "") + "):",
             "", "![success against training](curve.png)", ""]
    col = "| task " if len(tasks) > 1 else ""
    lines += [f"{col}| step | trainer wall hours | success | 95% Wilson |",
              "|---" * (4 + bool(col)) + "|"]
    for r in sorted(rows, key=lambda r: (r.get("task", DEFAULT_TASK), r["step"])):
        cell = f"| {r.get('task', DEFAULT_TASK)} " if col else ""
        lines.append(f"{cell}| {r['step']} | {r['train_hours']:.2f} | {r['successes']}/"
                     f"{r['episodes']} | {100 * r['ci95'][0]:.1f}-{100 * r['ci95'][1]:.1f}% |")
    return lines


#: Card title and lerobot class per policy type (sidecars from before ACT have no type).
POLICY_NAMES = {"diffusion": ("Diffusion Policy", "DiffusionPolicy"), "act": ("ACT", "ACTPolicy")}


def model_card(train_info: dict, evals: dict | list[dict] | None, curve: list[dict],
               hardware: str, also: list[dict] | None = None,
               success_curve: list[dict] | None = None,
               name: str = "pick_place_diffusion", weights: str = "") -> str:
    """Markdown model card from the training sidecar, the loss curve and harness results (one
    per task the checkpoint answers for)."""
    t = train_info
    evals = [evals] if isinstance(evals, dict) else list(evals or [])
    tasks = [e["config"]["task"] for e in evals] or [Path(t.get("dataset_task")
                                                          or DEFAULT_TASK).stem]
    title, cls = POLICY_NAMES.get(t.get("policy_type", "diffusion"),
                                  (t.get("policy_type"), "policy"))
    lines = [
        f"# {name}: {title} for so101_sim/PickPlace-v0, "
        + ("task " if len(tasks) == 1 else "tasks ") + ", ".join(tasks), "",
        f"lerobot `{cls}` (EMA weights, stored fp16, loaded as fp32), trained with "
        "`so101-sim train` on scripted-expert demonstrations"
        + (" of all these tasks, with no task input (each scene looks different)."
           if len(tasks) > 1 else "."), "",
        "| item | value |", "|---|---|",
        f"| preset | `{t['preset']}` (policy/presets/{t['preset']}.toml) |",
        f"| data | {t['dataset_episodes']} expert episodes, {t['dataset_frames']} frames, "
        f"recorded at {t['dataset_image_size'][0]}x{t['dataset_image_size'][1]}, "
        f"training seeds{_recording_note(t['dataset'])} |",
        *([f"| evaluation seeds in the data | "
           f"{ranges_text(t['dataset_eval_seeds'])} (rollouts; "
           "eval and export refuse to measure it on them) |"] if t.get("dataset_eval_seeds")
          else []),
        f"| policy input | 2 cameras resized to {t['policy_image_size'][0]}x"
        f"{t['policy_image_size'][1]} by {t['image_pipeline']} |",
        f"| steps | {t['step']} of {t['total_steps']} planned, batch {t['batch_size']} |",
        *([f"| started from | `{checkpoint_name(Path(t['init_from']['path']))}`, step "
           f"{t['init_from'].get('step')} (model.safetensors sha256 "
           f"{t['init_from']['model_sha256']}), fine-tuned on the data above |"]
          if t.get("init_from") else []),
        f"| precision | {_precision(t)} |",
        *([f"| shipped without | ACT's VAE encoder ({t['dropped_training_only'] / 1e6:.2f}M "
           "parameters; it only encodes demo actions in training, inference feeds a zero "
           "latent), so `use_vae` is false here |"] if t.get("dropped_training_only") else []),
        f"| trainer wall time | {t['train_wall_s'] / 3600:.2f} h (while the trainer ran, "
        "including time paused or sharing the CPU) |",
        f"| hardware | {hardware} |",
        *([f"| weights | `{weights}` (an eval of these weights has it as "
           "`config.policy_weights`) |"] if weights else []),
    ]
    for e in evals:
        lines += _eval_rows(e, "success" if len(evals) == 1 else
                            f"success on {e['config']['task']}")
    for other in also or []:
        lines += _eval_rows(other, "also measured")
    if not evals:
        lines.append("| success | not measured yet |")
    if curve:
        lines += ["", "Training loss (mean over each logging window):", "",
                  "| step | loss | lr | samples/s |", "|---|---|---|---|"]
        lines += [f"| {r['step']} | {r['loss']:.4f} | {r['lr']:.2e} | {r['samples_per_s']} |"
                  for r in curve]
    if success_curve:
        lines += _success_rows(success_curve)
    flag = "" if tasks == [DEFAULT_TASK] else f" --task {','.join(tasks)}"
    lines += ["", f"Evaluate: `so101-sim eval --policy {quote(f'policy/{name}')}{flag} "
              "--episodes 100`", ""]
    return "\n".join(lines)


def recorded_eval(folder: Path, task: str) -> Path:
    """The harness result an export stored for `task`: ``eval_info_<task>.json`` in a multi-task
    export, ``eval_info.json`` in a single-task one."""
    folder = Path(folder)
    per_task = folder / f"eval_info_{task}.json"
    return per_task if per_task.is_file() else folder / INFO


def _read_evals(eval_dirs: list[Path]) -> list[tuple[Path, dict]]:
    """(path, content) of each folder's eval_info.json; a `--task a,b` suite folder stands for
    its per-task folders."""
    found: list[tuple[Path, dict]] = []
    for folder in eval_dirs:
        path = Path(folder) / INFO
        if not path.is_file():
            raise FileNotFoundError(f"{path} does not exist; --eval takes a `so101-sim eval "
                                    "--out` folder")
        data = json.loads(path.read_text())
        if "per_task" in data:  # `so101-sim eval --task a,b`: one ordinary eval per task
            found += _read_evals([Path(folder) / e["task_group"] for e in data["per_task"]])
            continue
        check_eval_info(data, path)  # the card's numbers must be what eval wrote
        found.append((path, data))
    tasks = [e["config"]["task"] for _, e in found]
    if len(set(tasks)) < len(tasks):
        raise ValueError(f"--eval folders measure a task twice ({sorted(tasks)}); give one "
                         "eval per task (more of the same task go in --also-eval)")
    return found


def check_measured(evals: list[tuple[Path, dict]], digest: str, checkpoint: Path,
                   log: Callable[[str], None] = print) -> None:
    """Refuse an eval of other weights than `checkpoint`'s (digest `digest`): its numbers
    would go into this card. An eval written before evals recorded their weights gets one
    line saying it was not checked."""
    for path, e in evals:
        measured = e["config"].get("policy_weights")
        if measured is None and "software" in e["config"]:  # recorded after the weights were
            raise ValueError(f"{path} measured {e['config']['policy']}, which has no "
                             f"checkpoint weights, not {checkpoint}; evaluate this checkpoint "
                             "or its export and pass that folder")
        if measured is None:
            log(f"so101-sim export: note: {path} names no weights (an eval from before "
                "they were recorded); not checked that it measured this checkpoint")
        elif measured != digest:
            raise ValueError(f"{path} measured other weights ({e['config']['policy']}, "
                             f"weights {measured}) than {checkpoint} (weights {digest}); "
                             "evaluate this checkpoint or its export and pass that folder")
        try:  # a card's rate is on held-out seeds, never on rollouts it was trained on
            task = load_task(e["config"]["task"])
        except TaskSpecError:
            continue  # a task file from elsewhere: its scenes are not known here
        try:
            check_unseen_seeds(demos_of(checkpoint), task,
                               [p["seed"] for p in e["per_episode"]], False)
        except ValueError as exc:
            raise ValueError(f"{path} cannot go into the card: {exc}") from None


def check_dest(dest: Path, digest: str, replace: bool) -> None:
    """`dest` is replaced whole: refuse a folder of other files, and another checkpoint's
    export unless `replace`. The same checkpoint again (e.g. with its eval) is fine."""
    if not dest.exists() or (dest.is_dir() and not any(dest.iterdir())):
        return
    model = dest / "model.safetensors"
    if not dest.is_dir():
        raise ValueError(f"--out {dest} is a file; expected a folder for the export: choose "
                         "another --out")
    if not model.is_file() or not (dest / "config.json").is_file():
        raise ValueError(f"--out {dest} holds other files, not an exported policy, and an "
                         "export replaces its folder whole; choose a new or empty folder")
    if replace:  # whatever it holds, even a damaged copy
        return
    try:
        held = weights_digest(model)
    except ValueError as exc:
        raise ValueError(f"--out {dest} holds a damaged export ({exc}); pass --replace to "
                         "overwrite it") from None
    if held != digest:
        raise ValueError(f"--out {dest} already holds another policy (weights {held}; this "
                         f"checkpoint's are {digest}); pass --replace to overwrite it, after "
                         "`so101-sim compare` shows the new one is better, or choose "
                         "another --out")


def check_not_itself(checkpoint: Path, dest: Path) -> None:
    """An export in place would rewrite the checkpoint's own folder, card included, from a
    folder with no training run beside it (its log and curve gone); inside it, among its files."""
    here, there = checkpoint.resolve(), dest.resolve()
    if there == here:
        raise ValueError(f"--out {dest} is the checkpoint itself; an export rewrites its folder "
                         "whole, and the card's training log and curve come from the run the "
                         "checkpoint was trained in, so they would be lost: export the run's "
                         "checkpoint again (so101-sim export RUN/pretrained_model --out "
                         f"{quote(str(dest))} --eval EVAL), or choose another --out")
    if here in there.parents:
        raise ValueError(f"--out {dest} lies inside the checkpoint {checkpoint}; choose a "
                         "folder outside it")


def training_run(checkpoint: Path) -> Path | None:
    """The `so101-sim train` run folder a checkpoint belongs to (its log and curve), if any:
    RUN/checkpoints/step_N/pretrained_model or RUN/pretrained_model."""
    if checkpoint.parent.parent.name == "checkpoints":
        return checkpoint.parents[2]
    if (checkpoint.parent / "train_log.jsonl").is_file():
        return checkpoint.parent
    return None


def check_readable(checkpoint: Path) -> None:
    """Every safetensors file of `checkpoint` opens: a torn one is refused before it ships."""
    from safetensors import safe_open

    for f in sorted(checkpoint.glob("*.safetensors")):
        try:
            with safe_open(f, "pt"):
                pass
        except Exception as exc:  # safetensors' own error type
            raise damaged(f, exc) from None


def export_lock(dest: Path) -> Path:
    """The lock file of an export to `dest`: `dest` is replaced whole, so it lives beside it."""
    return dest.parent / f".{dest.name}.export.lock"


def export_policy(checkpoint: Path, dest: Path,
                  eval_dir: Path | Sequence[Path] | None = None,
                  hardware: str = "2-core CPU (no GPU)",
                  also_eval: list[Path] | None = None, replace: bool = False,
                  log: Callable[[str], None] = print) -> Path:
    """Copy `checkpoint` (a pretrained_model folder) to `dest` with fp16 weights and a card.

    `eval_dir`: one eval folder, several (one per task), or a multi-task suite eval folder;
    each must have measured these weights. `replace`: `dest` may hold another policy."""
    checkpoint, dest = Path(checkpoint), Path(dest)
    info_path = checkpoint / TRAIN_INFO
    if not (checkpoint / "model.safetensors").is_file() or not info_path.is_file():
        # only folders export takes: a lerobot-train checkpoint has no so101-sim sidecar
        near = " or ".join(str(p) for p in nearby_policies(checkpoint)
                           if (p / TRAIN_INFO).is_file())
        raise FileNotFoundError(f"{checkpoint} is not a so101-sim checkpoint (needs "
                                f"model.safetensors and {TRAIN_INFO}); "
                                + (f"did you mean {near}?" if near else other_kind(checkpoint) +
                                   "pass a run's pretrained_model folder (RUN/pretrained_model "
                                   "or RUN/checkpoints/step_*/pretrained_model)"))
    check_not_itself(checkpoint, dest)  # after: a folder that is no checkpoint is the error
    check_processor_files(checkpoint)  # never ship a file that would run code when loaded
    check_readable(checkpoint)
    dirs = [] if eval_dir is None else [eval_dir] if isinstance(eval_dir, (str, Path)) \
        else list(eval_dir)
    evals = _read_evals(dirs)
    also = _read_evals(also_eval or [])
    digest = weights_digest(checkpoint / "model.safetensors")
    check_measured(evals + also, digest, checkpoint, log)
    if folders := sorted(f.name for f in checkpoint.iterdir() if f.is_dir()):
        log(f"so101-sim export: note: {checkpoint} holds folders {folders}, which no checkpoint "
            "has (an eval's --out inside it, say); the export leaves them out")
    with folder_lock(dest.parent, f"the export {dest.name}", again="rerun",
                     name=export_lock(dest).name):
        check_dest(dest, digest, replace)
        return _export(checkpoint, dest, info_path, evals, hardware, [e for _, e in also],
                       digest)


def _export(checkpoint: Path, dest: Path, info_path: Path, evals: list[tuple[Path, dict]],
            hardware: str, also: list[dict], digest: str) -> Path:
    info = json.loads(info_path.read_text())
    tasks = [e["config"]["task"] for _, e in evals] or [info.get("dataset_task") or DEFAULT_TASK]
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(checkpoint, tmp, ignore=lambda _, names: [  # the files, fp16 below
            n for n in names if n == "model.safetensors" or (checkpoint / n).is_dir()])
        act_vae = _drop_act_vae(tmp)
        dropped = _fp16_copy(checkpoint / "model.safetensors", tmp / "model.safetensors",
                             drop=ACT_TRAINING_ONLY if act_vae else None)
        if dropped:
            info = {**info, "dropped_training_only": dropped}
        for path, e in evals:
            shutil.copy(path, tmp / (INFO if len(evals) == 1
                                     else f"eval_info_{e['config']['task']}.json"))
        run = training_run(checkpoint)
        log = run / "train_log.jsonl" if run else None
        curve = loss_curve(log) if log and log.is_file() else []
        curve = [r for r in curve if r["step"] <= info["step"]]
        success_curve = widest_rows([r for task in tasks for r in read_curve(run, task)
                                     if r["step"] <= info["step"]]) if run else []
        if success_curve:
            plot_curve(success_curve, tmp / "curve.png")
        card = model_card(info, [e for _, e in evals], curve, hardware, also, success_curve,
                          name=dest.name, weights=digest)
        (tmp / "README.md").write_text(card)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # a full disk: free what this run took
        raise
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return dest

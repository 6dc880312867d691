"""Turning a ``--policy`` argument into an ``EvalPolicy``: the expert, a lerobot checkpoint
directory, or a ``package.module:factory`` of your own. Checkpoints load lazily (torch)."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from so101_sim.expert import ScriptedExpert
from so101_sim.harness.policies.checks import flag_names
from so101_sim.harness.policies.protocol import EvalPolicy, PolicyInfo, StepPolicy
from so101_sim.tasks import DEFAULT_TASK, TaskSpec, load_task


def refuse_options(options: dict[str, Any], policy: str) -> None:
    """Options only a lerobot checkpoint reads, given to another policy: refused, not
    ignored."""
    if options:
        named = flag_names(options)
        raise ValueError(f"{named} appl{'y' if len(options) > 1 else 'ies'} to lerobot "
                         f"checkpoints, not to --policy {policy}; drop "
                         f"{'them' if len(options) > 1 else 'it'}")


def expert_policy(task: str | Path | TaskSpec = DEFAULT_TASK) -> StepPolicy:
    """The scripted expert as an ``EvalPolicy`` (reads the true cube pose: no cameras)."""
    spec = load_task(task)
    return StepPolicy(lambda: ScriptedExpert(spec),
                      PolicyInfo(name="expert", needs_env_state=True,
                                 fingerprint=f"so101_sim.expert.ScriptedExpert/{spec.name}"))


def load_policy(spec: str | Path, task: str | Path | TaskSpec = DEFAULT_TASK,
                **lerobot_options: Any) -> EvalPolicy:
    """``"expert"``, ``"baseline"`` (the shipped checkpoint for `task`), a lerobot checkpoint
    directory, or ``"package.module:factory"`` (a callable taking ``task`` and returning an
    ``EvalPolicy``)."""
    text = str(spec)
    if text == "baseline":  # the shipped checkpoint for this task (policy/baselines.toml)
        from so101_sim.harness.baselines import baseline_checkpoint

        text = str(baseline_checkpoint(load_task(task)))
    if text == "expert":
        refuse_options(lerobot_options, text)
        return expert_policy(task)
    path = Path(text).expanduser()
    if not path.exists() and ":" in text and "/" not in text.split(":", 1)[0]:
        refuse_options(lerobot_options, text)  # a factory takes only the task
        return _load_factory(text, task)
    from so101_sim.harness.policies.lerobot import LeRobotPolicy

    return LeRobotPolicy(path, task_description=load_task(task).description, **lerobot_options)


def _load_factory(text: str, task: str | Path | TaskSpec) -> EvalPolicy:
    module_name, _, attr = text.partition(":")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"--policy {text!r}: cannot import {attr!r} from {module_name!r} "
                         f"({exc}); expected 'expert', a checkpoint directory or "
                         "'package.module:factory'") from exc
    policy = factory(task=task)
    if not isinstance(policy, EvalPolicy):
        raise ValueError(f"--policy {text!r} returned {type(policy).__name__}, which lacks "
                         "`info`, `start_episode` or `predict_chunks` (see "
                         "so101_sim.harness.EvalPolicy)")
    return policy

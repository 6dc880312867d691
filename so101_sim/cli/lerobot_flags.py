"""lerobot's flags given to `so101-sim`: answered with the command line that works.

The README runs lerobot-eval and lerobot-train beside `so101-sim eval` and `train`, so their
draccus spellings (`--policy.path=P`, `--eval.n_episodes=N`) reach this CLI too. Matched by
spelling alone, `--policy.path` is nearest `--policy-batch`, a wrong hint; these maps say
what each one means here. `None`: the flag has no counterpart and is left out.
"""

from __future__ import annotations

from shlex import join

__all__ = ["LEROBOT_FLAGS", "PRESET_OF_POLICY_TYPE", "rewrite_lerobot_flags"]

_POLICY = {"--policy.n_action_steps": "--n-action-steps",
           "--policy.num_inference_steps": "--inference-steps",
           "--policy.noise_scheduler_type": "--noise-scheduler",
           "--policy.temporal_ensemble_coeff": "--temporal-ensemble"}
_EVAL = {"--eval.n_episodes": "--episodes", "--eval.batch_size": "--n-envs",
         "--eval.use_async_envs": None, "--env.type": None, "--env.task": "--task"}

LEROBOT_FLAGS: dict[str, dict[str, str | None]] = {
    "eval": {"--policy.path": "--policy", "--policy.device": "--device",
             "--output_dir": "--out", "--workers": "--n-envs", **_EVAL, **_POLICY},
    "curve": {"--workers": "--n-envs", **_EVAL,
              "--policy.temporal_ensemble_coeff": "--temporal-ensemble"},
    "train": {"--dataset.root": "--dataset", "--output_dir": "--out",
              "--policy.path": "--init-from", "--policy.device": "--device",
              "--batch_size": "--batch-size", "--dataset.repo_id": None,
              "--policy.type": "--preset", "--env.type": None},
    "record": {"--dataset.root": "--out", "--dataset.num_episodes": "--episodes",
               "--dataset.repo_id": None, "--n-envs": "--workers", "--env.task": "--task"},
    "explain": {"--dataset.root": "--dataset", "--policy.path": "--policy",
                "--output_dir": "--out", "--dataset.repo_id": None},
    "replay": {"--dataset.root": "", "--dataset.episode": "--episode",
               "--dataset.repo_id": None, "--robot.type": None},
    "export": {"--policy.path": ""},
    "compare": {"--output_dir": "--out"},
    "demo": {"--output_dir": "--out", "--env.task": "--task"},
}
"""Per command: a lerobot flag (or another command's spelling) -> this command's flag; ""
for its positional argument (the value alone)."""

PRESET_OF_POLICY_TYPE = {"diffusion": "cpu"}
"""lerobot's `--policy.type` -> train's `--preset` (`act` is both)."""


def rewrite_lerobot_flags(words: list[str], extras: list[str]) -> str | None:
    """`so101-sim WORDS` with each flag of `extras` that `LEROBOT_FLAGS` maps put in this
    command's spelling; None when none of them is mapped."""
    name = words[0]
    mapping = LEROBOT_FLAGS.get(name, {})
    if not any(e.partition("=")[0] in mapping for e in extras):
        return None
    fixed: list[str] = []
    rest = iter(enumerate(words))
    for i, word in rest:
        flag, eq, value = word.partition("=")
        if word not in extras or flag not in mapping:
            fixed.append(word)
            continue
        if not eq and i + 1 < len(words) and not words[i + 1].startswith("-"):
            value = next(rest)[1]  # `--flag value`
        new = mapping[flag]
        if new == "--preset":
            value = PRESET_OF_POLICY_TYPE.get(value, value)
        if new is not None:
            fixed.extend([w for w in (new, value) if w])
    return f"so101-sim {join(fixed)}"

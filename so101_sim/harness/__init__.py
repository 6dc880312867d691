"""Rollout harness: evaluate a policy on many seeds in parallel envs, with reports.

``evaluate(policy, episodes=..., n_envs=...)`` runs it (``so101-sim eval`` on the command
line); a policy is ``"expert"``, a lerobot checkpoint directory, or any object following
``EvalPolicy``. Importing this package loads no torch: the lerobot adapter does, on use.
"""

from so101_sim.harness.policies import (
    ChunkRequest,
    EvalPolicy,
    PolicyInfo,
    StepPolicy,
    expert_policy,
    load_policy,
)
from so101_sim.harness.runner import evaluate

__all__ = ["ChunkRequest", "EvalPolicy", "PolicyInfo", "StepPolicy", "evaluate",
           "expert_policy", "load_policy"]

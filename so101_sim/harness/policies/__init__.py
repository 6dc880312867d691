"""Policies the harness evaluates: the protocol (``EvalPolicy``), and adapters for the scripted
expert, step-wise controllers and lerobot checkpoints (loaded lazily: no torch on import)."""

from so101_sim.harness.policies.factory import expert_policy, load_policy
from so101_sim.harness.policies.protocol import (
    ChunkRequest,
    EvalPolicy,
    PolicyInfo,
    StepPolicy,
    spare_core,
)

__all__ = ["ChunkRequest", "EvalPolicy", "PolicyInfo", "StepPolicy", "expert_policy",
           "load_policy", "spare_core"]

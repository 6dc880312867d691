"""lerobot's policy server, unchanged but for one fix: a Diffusion Policy with n_obs_steps > 1
runs on it (lerobot 0.6.1's fails, huggingface/lerobot#3861).

    python -m lerobot_robot_so101_sim.patched_server --host=127.0.0.1 --port=8080 --fps=30

The flags are lerobot's own (``PolicyServerConfig``). ``agreement.py async --patch-diffusion``
starts it. lerobot's robot client asking for ``--policy_type=diffusion`` is refused at connect
unless it adds ``--robot.patched_server=true``: the robot cannot tell which server the client
talks to. Not imported by the plugin's ``__init__``: lerobot's CLIs import the plugin at
start-up and must not get the patch.
"""

from __future__ import annotations

from typing import Any

__all__ = ["patch_diffusion_single_observation", "serve"]


def patch_diffusion_single_observation() -> None:
    """lerobot 0.6.1's server calls ``predict_action_chunk`` with one observation and empty
    history queues; a Diffusion Policy with n_obs_steps > 1 then fails an assertion. Repeat
    that observation over the history first (what ``select_action`` does at an episode's
    start; the fix proposed upstream, huggingface/lerobot PR 3886). Patching twice is a no-op.
    """
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

    original = DiffusionPolicy.predict_action_chunk
    if getattr(original, "so101_sim_patched", False):
        return

    def predict_action_chunk(self: Any, batch: dict, noise: Any = None) -> Any:
        if not any(len(q) for q in self._queues.values()):
            n, batch = self.config.n_obs_steps, dict(batch)
            for key in (OBS_STATE, OBS_ENV_STATE, *self.config.image_features):
                value = batch.get(key)
                if value is not None and value.ndim in (2, 4):  # no history axis yet
                    batch[key] = value.unsqueeze(1).repeat_interleave(n, dim=1)
        return original(self, batch, noise=noise)

    predict_action_chunk.so101_sim_patched = True  # type: ignore[attr-defined]
    DiffusionPolicy.predict_action_chunk = predict_action_chunk


def serve() -> None:
    """Patch, then run lerobot's ``serve`` on this process's command line."""
    patch_diffusion_single_observation()
    from lerobot.async_inference import policy_server

    policy_server.serve()


if __name__ == "__main__":
    serve()

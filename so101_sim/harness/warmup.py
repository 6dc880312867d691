"""Start the env workers' fork server while the policy loads, so their imports overlap.

``so101-sim eval`` spends its first seconds importing torch and lerobot and loading the
checkpoint on one core, and only then starts the env workers, whose fork server imports
MuJoCo and torch (for the in-worker resize) on its own: 8 s and then 4.5 s on the 2-core Xeon
of benchmarks/README.md. Started first, the fork server imports on the other core while the
checkpoint loads. Nothing a worker computes changes: it forks from the same server with the
same modules, only sooner.
"""

from __future__ import annotations

__all__ = ["warm_eval_workers", "worker_preload"]


def worker_preload(*, resize: bool, rollouts: bool, videos: bool) -> tuple[str, ...]:
    """Modules the fork server imports once for every eval worker (torch for in-worker
    resizes; the video writer's cv2 and imageio, about 0.06 s a worker, when any episode is
    filmed)."""
    mods = ["so101_sim.sim.env"]
    if videos:
        mods.append("so101_sim.harness.video")
    if resize:
        mods.append("so101_sim.utils.image_pipeline")
    if rollouts:
        mods += ["so101_sim.harness.rollout_tape", "lerobot.datasets.video_utils"]
    return tuple(mods)


def warm_eval_workers(*, videos: bool, rollouts: bool = False) -> bool:
    """Choose the GL backend and start the fork server now (local workers only).

    The GL choice comes first because workers inherit the fork server's environment, which
    is fixed when it starts. Returns False, starting nothing, where no headless GL works
    (the eval then fails or runs without rendering exactly as it would have).
    """
    from so101_sim.sim.rendering import select_gl_backend
    from so101_sim.workers.local import start_fork_server

    try:
        select_gl_backend()
    except RuntimeError:
        return False
    start_fork_server(worker_preload(resize=True, rollouts=rollouts, videos=videos))
    return True

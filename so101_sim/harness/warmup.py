"""Start the env workers' fork server, and the render self-check, while the policy loads.

``so101-sim eval`` spends its first seconds importing torch and lerobot and loading the
checkpoint on one core, and only then starts the env workers, whose fork server imports
MuJoCo and torch (for the in-worker resize) on its own: 8 s and then 4.5 s on the 2-core Xeon
of benchmarks/README.md. Started first, the fork server imports on the other core while the
checkpoint loads. Nothing a worker computes changes: it forks from the same server with the
same modules, only sooner.

The render self-check (``harness.frames``: about a second of building scenes and rendering
reset frames) needs only the checkpoint's JSON files and the task, so ``start_self_check``
runs it in a process forked from that server, on the core the driver's imports leave free;
``choose_rendering`` takes its answer if it was asked the same question, else checks itself.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["EarlySelfCheck", "start_self_check", "warm_eval_workers", "worker_preload"]


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


class EarlySelfCheck:
    """``harness.frames.self_check`` running in a process forked from the fork server."""

    def __init__(self, task: Any, cameras: tuple[str, ...], recorded: tuple[int, int],
                 inp: tuple[int, int], timeout_s: float = 120.0) -> None:
        import multiprocessing as mp

        ctx = mp.get_context("forkserver")
        self._conn, self._child = ctx.Pipe(duplex=False)
        self.timeout_s = timeout_s
        self._proc = ctx.Process(target=_run_check,
                                 args=(self._child, task, cameras, recorded, inp),
                                 name="so101-eval-self-check", daemon=True)
        self._started = False
        # Process.start() waits until the fork server has imported its modules and forked:
        # a thread waits for it, so the imports here go on meanwhile.
        self._starter = threading.Thread(target=self._start, name="so101-self-check-start",
                                         daemon=True)
        self._starter.start()

    def _start(self) -> None:
        try:
            self._proc.start()
            self._started = True
        except Exception:  # no fork server after all: result() says None
            pass
        finally:
            self._child.close()

    def result(self) -> tuple | None:
        """The check's (size, numbers), or None if it failed or took too long (the caller
        then checks in its own process, where a failure is reported as before)."""
        deadline = time.monotonic() + self.timeout_s
        self._starter.join(self.timeout_s)
        try:
            if not self._started or not self._conn.poll(max(0.0, deadline - time.monotonic())):
                if self._started:
                    self._proc.terminate()
                return None
            ok, value = self._conn.recv()
        except (EOFError, OSError):
            return None
        finally:
            self._conn.close()
        self._proc.join(timeout=5)
        return value if ok else None


def _run_check(conn: Any, task: Any, cameras: tuple[str, ...], recorded: tuple[int, int],
               inp: tuple[int, int]) -> None:
    from so101_sim.harness.frames import self_check

    try:
        try:
            reply = (True, self_check(task, cameras, recorded, inp))
        except Exception as exc:  # any failure: the driver checks again and reports it there
            reply = (False, repr(exc))
        conn.send(reply)
    except OSError:  # the driver stopped first (e.g. it refused a flag): nobody to tell
        pass
    finally:
        conn.close()


def start_self_check(checkpoint: Path, task: str, camera_map: dict[str, str] | None = None
                     ) -> bool:
    """Start the render self-check of `checkpoint` on `task` in the background, if it will
    be needed (a checkpoint trained on frames larger than its input); False if not started.

    Reads only config.json and the training info, without lerobot: anything unusual starts
    nothing, and loading the checkpoint then reports it as it always did.
    """
    from so101_sim.harness.camera_map import resolve_camera_map
    from so101_sim.harness.frames import check_key, expect_self_check
    from so101_sim.tasks import ALL_CAMERAS, load_task
    from so101_sim.train.checkpoint import image_input_shapes, train_image_size

    try:
        shapes = image_input_shapes(checkpoint)
        sizes = {shape[1:] for shape in shapes.values()}
        if len(sizes) != 1:
            return False
        inp = sizes.pop()
        recorded = train_image_size(checkpoint) or inp
        if recorded == inp or len(inp) != 2:
            return False
        mapping = resolve_camera_map(shapes, camera_map, str(checkpoint), log=lambda _: None)
        spec = load_task(task)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    cameras = tuple(c for c in ALL_CAMERAS if c in mapping.values())
    key = check_key(spec, cameras, recorded, inp)
    expect_self_check(key, EarlySelfCheck(spec, cameras, recorded, inp))
    return True

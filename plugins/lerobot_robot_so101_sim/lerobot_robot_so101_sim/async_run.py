"""lerobot's async inference driving the sim for N episodes: its policy server in a subprocess
on a loopback port, its ``RobotClient`` in this process, unchanged but for a clock on each
action chunk. ``agreement.py async`` runs it; not imported by the plugin's ``__init__`` (it
imports lerobot's gRPC client).
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["AsyncRun", "log_tail", "run_async"]


@dataclass(frozen=True, kw_only=True)
class AsyncRun:
    """What one run needs besides the robot's config fields (``robot_flags``): lerobot's
    ``RobotClientConfig`` values, the task (its fps and description) and when to stop."""

    policy_path: Path
    policy_type: str
    task: Any  # a so101_sim TaskSpec
    episodes: int
    actions_per_chunk: int
    chunk_size_threshold: float
    aggregate_fn: str
    port: int = 0  # 0: a free one
    patch_diffusion: bool = False  # serve with lerobot_robot_so101_sim.patched_server


def log_tail(log: Path) -> str:
    """The end of a subprocess's log, for an error message."""
    return log.read_text(encoding="utf-8", errors="replace")[-3000:]


def run_async(run: AsyncRun, out: Path, robot_flags: dict[str, Any]) -> list[float]:
    """Serve, drive ``run.episodes`` episodes to their end, stop both; returns each chunk's
    latency (s) from its observation's capture to its arrival. Errors end in SystemExit with
    the end of ``out/server.log``."""
    port = run.port or _free_port()
    server_module = ("lerobot_robot_so101_sim.patched_server" if run.patch_diffusion else
                     "lerobot.async_inference.policy_server")
    serve = [sys.executable, "-m", server_module, "--host=127.0.0.1", f"--port={port}",
             f"--fps={run.task.fps}"]
    with open(out / "server.log", "w", encoding="utf-8") as log:  # cwd: its logs/ in out
        server = subprocess.Popen(serve, stdout=log, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, cwd=out)
    try:
        _wait_for_port(port, server)
        return _client(run, port, out, robot_flags)
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for_port(port: int, server: subprocess.Popen, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if server.poll() is not None:
            raise SystemExit(f"the policy server exited with {server.returncode} before "
                             "listening; see server.log in --out")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise SystemExit(f"the policy server did not listen on port {port} within {timeout:.0f} s")


def _client(run: AsyncRun, port: int, out: Path, robot_flags: dict[str, Any]) -> list[float]:
    from lerobot.async_inference.configs import RobotClientConfig

    from lerobot_robot_so101_sim.config import SO101SimConfig

    with contextlib.chdir(out):  # importing it makes logs/ and a log file in the cwd
        from lerobot.async_inference.robot_client import RobotClient

    latencies: list[float] = []

    class TimedClient(RobotClient):
        """lerobot's client, unchanged, noting when each chunk arrives: the chunk's first
        action carries the capture time of the observation it was computed from."""

        def _aggregate_action_queues(self, incoming_actions: list, aggregate_fn: Any = None
                                     ) -> None:
            if incoming_actions:
                latencies.append(time.time() - incoming_actions[0].get_timestamp())
            super()._aggregate_action_queues(incoming_actions, aggregate_fn)

    robot = SO101SimConfig(**robot_flags, episode_end="reset")
    cfg = RobotClientConfig(
        policy_type=run.policy_type, robot=robot,  # the server's cwd is out
        pretrained_name_or_path=str(run.policy_path.resolve()),
        actions_per_chunk=run.actions_per_chunk, task=run.task.description,
        server_address=f"127.0.0.1:{port}", policy_device="cpu",
        chunk_size_threshold=run.chunk_size_threshold, fps=run.task.fps,
        aggregate_fn_name=run.aggregate_fn)
    client = TimedClient(cfg)
    if not client.start():  # the server raised on the policy (its traceback is in its log),
        # or stopped listening
        client.stop()
        log = out / "server.log"
        raise SystemExit(f"the policy server on port {port} did not take --policy "
                         f"{run.policy_path}; the end of {log}:\n{log_tail(log)}")
    threads = [threading.Thread(target=client.receive_actions, daemon=True),
               threading.Thread(target=client.control_loop, args=(run.task.description,),
                                daemon=True)]
    for t in threads:
        t.start()
    print(f"agreement: {run.episodes} episodes through async inference on port {port}",
          flush=True)
    sim = client.robot
    try:
        while sum(o["ended_by"] == "env" for o in sim.outcomes) < run.episodes:
            if not threads[1].is_alive():
                raise SystemExit("the robot client's control loop stopped; see the log above")
            time.sleep(0.2)
    finally:
        client.shutdown_event.set()
        threads[1].join(timeout=30)
        client.stop()
        threads[0].join(timeout=30)
    return latencies

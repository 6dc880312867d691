"""eval and record on a real two-node Ray cluster on this machine.

The test starts ``ray start --head`` on a loopback port and a second ``ray start --address``
node with its own CPUs, runs ``so101-sim eval`` and ``so101-sim record`` against it with
``--ray-address``, checks that the actors ran on both nodes and that the results equal the
local backend's, and tears both nodes down (SIGTERM, then SIGKILL of their process groups),
every step with a bounded timeout.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("ray")

from so101_sim.dataset import stored_seeds
from so101_sim.harness import evaluate
from so101_sim.record import record

BIN = Path(sys.executable).parent
KEYS = ("seed", "success", "failure_mode", "steps", "actions_sha")
ENV = {**os.environ, "RAY_AUTH_MODE": "disabled", "HF_HUB_OFFLINE": "1",
       "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
pytestmark = [pytest.mark.slow, pytest.mark.ray_cluster]
NODES: dict[str, subprocess.Popen] = {}  # the second node's `ray start --block` process


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(args: list[str], log: Path) -> subprocess.Popen:
    with log.open("w") as f:  # its own session: teardown can reach every process it starts
        return subprocess.Popen([str(BIN / "ray"), "start", *args, "--disable-usage-stats",
                                 "--object-store-memory", "100000000", "--block"], env=ENV,
                                stdout=f, stderr=subprocess.STDOUT, start_new_session=True)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)  # `ray start --block` stops what it started
    deadline = time.monotonic() + 90
    for p in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=max(1.0, deadline - time.monotonic()))
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)  # anything of that session still alive


def _alive_nodes(address: str) -> int:
    code = (f"import ray; ray.init(address={address!r}, logging_level='ERROR'); "
            "print(sum(n['Alive'] for n in ray.nodes()))")
    try:
        out = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True,
                             text=True, timeout=60)
        return int(out.stdout.strip().splitlines()[-1])
    except (subprocess.TimeoutExpired, ValueError, IndexError):
        return 0


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[str]:
    logs = tmp_path_factory.mktemp("ray_logs")
    port = _free_port()
    address = f"127.0.0.1:{port}"
    procs = [_start(["--head", "--port", str(port), "--node-ip-address", "127.0.0.1",
                     "--num-cpus", "1", "--include-dashboard", "false"], logs / "head.log")]
    try:
        deadline = time.monotonic() + 120
        while True:  # the head's GCS answers on the port
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline or procs[0].poll() is not None:
                    pytest.fail("ray head did not start: "
                                + (logs / "head.log").read_text()[-2000:])
                time.sleep(0.5)
        procs.append(_start(["--address", address, "--node-ip-address", "127.0.0.1",
                             "--num-cpus", "2"], logs / "node.log"))
        NODES["worker"] = procs[1]  # the node-loss test (last in this file) stops it
        deadline = time.monotonic() + 180
        while _alive_nodes(address) < 2:
            if time.monotonic() > deadline or procs[1].poll() is not None:
                pytest.fail("second ray node did not join: "
                            + (logs / "node.log").read_text()[-2000:])
            time.sleep(1)
        yield address
    finally:
        _stop(procs)
        current = Path("/tmp/ray/ray_current_cluster")  # `ray start` wrote our address there
        if current.exists() and current.read_text().strip().endswith(f":{port}"):
            current.unlink()


def _cli(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "so101-sim"), *args], env=ENV, capture_output=True,
                          text=True, timeout=timeout)


def test_eval_and_record_on_a_two_node_cluster(cluster: str, tmp_path: Path) -> None:
    local = evaluate("expert", episodes=4, n_envs=1, videos=0, report=False,
                     out_dir=tmp_path / "local", progress=False, log=lambda _: None)
    out = _cli("eval", "--policy", "expert", "--episodes", "4", "--n-envs", "3",
               "--videos", "1", "--image-size", "48x64", "--out", str(tmp_path / "ray"),
               "--backend", "ray", "--ray-address", cluster)
    assert out.returncode == 0, out.stderr[-3000:]
    info = json.loads((tmp_path / "ray" / "eval_info.json").read_text())
    assert info["config"]["workers"]["nodes"] == 2, info["config"]["workers"]
    assert info["config"]["workers"]["address"] == cluster
    ours = [tuple(e[k] for k in KEYS) for e in info["per_episode"]]
    assert ours == [tuple(e[k] for k in KEYS) for e in local["per_episode"]]
    assert (tmp_path / "ray" / "videos" / "episode_0000_seed100000.mp4").exists()

    record(tmp_path / "ds_local", 2, image_size=(48, 64), progress=False)
    out = _cli("record", "--episodes", "2", "--workers", "2", "--image-size", "48x64",
               "--out", str(tmp_path / "ds_ray"), "--backend", "ray", "--ray-address", cluster)
    assert out.returncode == 0, out.stderr[-3000:]
    assert stored_seeds(tmp_path / "ds_ray") == stored_seeds(tmp_path / "ds_local") == [0, 1]
    a = sorted((tmp_path / "ds_local" / "data").rglob("*.parquet"))
    b = sorted((tmp_path / "ds_ray" / "data").rglob("*.parquet"))
    import pyarrow.parquet as pq

    cols = ["action", "observation.state", "episode_seed", "frame_index"]
    rows_a = [row for f in a for row in pq.read_table(f, columns=cols).to_pylist()]
    rows_b = [row for f in b for row in pq.read_table(f, columns=cols).to_pylist()]
    assert rows_a == rows_b


def _crash_node(node: subprocess.Popen) -> None:
    """Kill every process of a node (its `ray start` session: raylet, agents and the actors'
    worker processes) at once, as a machine that drops off the network would."""
    sid = os.getsid(node.pid)
    ps = subprocess.run(["ps", "-eo", "pid,sid"], capture_output=True, text=True).stdout
    for line in ps.splitlines()[1:]:
        pid, session = (int(v) for v in line.split())
        if session == sid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    node.wait(timeout=60)


def test_losing_a_node_mid_run_finishes_on_the_rest(cluster: str, tmp_path: Path) -> None:
    """The second node dies while an eval runs on both: its workers are replaced on the head
    node (oversubscribed), their episodes run again, and every seed's result equals a local
    run's. Kills that node: keep this test last in the file."""
    n = "36"  # episodes of ~0.3 s each on 3 workers: still running when the node is gone
    local = evaluate("expert", episodes=int(n), n_envs=2, videos=0, report=False,
                     out_dir=tmp_path / "local", progress=False, log=lambda _: None)
    out = tmp_path / "ray"
    proc = subprocess.Popen([str(BIN / "so101-sim"), "eval", "--policy", "expert",
                             "--episodes", n, "--n-envs", "3", "--videos", "0",
                             "--image-size", "48x64", "--out", str(out), "--backend", "ray",
                             "--ray-address", cluster], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 600
        log = out / "episodes.jsonl"
        while not (log.is_file() and log.read_text().count("\n") >= 1):  # both nodes busy
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        _crash_node(NODES["worker"])
        assert proc.poll() is None, "the eval ended before the node was lost"
        said, err = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-3000:]
    assert "restarts without a CPU reservation" in said + err
    info = json.loads((out / "eval_info.json").read_text())
    assert info["config"]["workers"]["restarts"] >= 1, info["config"]["workers"]
    assert info["config"]["reruns"], "no episode was cut short by the node loss"
    ours = [tuple(e[k] for k in KEYS) for e in info["per_episode"]]
    assert ours == [tuple(e[k] for k in KEYS) for e in local["per_episode"]]

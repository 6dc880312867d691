"""A Ray cluster that isn't there: one line in bounded time, no folder, signals that work.

``--ray-address`` pointing where nothing listens ends in one line naming the address and
``ray start --head --port P``; a port that accepts but never answers ends after
``--ray-connect-timeout``; Ctrl-C and SIGTERM end the run at once while it connects, while a
local runtime starts and while episodes run, and a run that never started leaves no folder
(and no Ray process) behind. Losing a node mid-run is in test_ray_cluster.py.
"""

from __future__ import annotations

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

EXE = str(Path(sys.executable).parent / "so101-sim")
ENV = {**os.environ, "RAY_AUTH_MODE": "disabled", "HF_HUB_OFFLINE": "1",
       "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
EVAL = ["eval", "--policy", "expert", "--episodes", "8", "--n-envs", "2", "--videos", "0",
        "--image-size", "48x64"]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nothing listens there once it is closed


@pytest.fixture
def silent_port() -> Iterator[int]:
    """A port that accepts connections (the kernel's backlog) and never says a word."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(64)
        yield s.getsockname()[1]


def _error_line(err: str) -> str:
    """The one error line (a progress bar may be redrawn after it)."""
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1, err[-2000:]
    return lines[0]


@pytest.mark.parametrize("command", ["eval", "record"])
def test_nothing_listening_is_one_line_and_no_folder(tmp_path: Path, command: str) -> None:
    port, out = _closed_port(), tmp_path / "out"
    argv = (EVAL if command == "eval" else ["record", "--episodes", "1", "--image-size",
                                           "48x64"])
    t0 = time.monotonic()
    r = subprocess.run([EXE, *argv, "--out", str(out), "--backend", "ray", "--ray-address",
                        f"127.0.0.1:{port}", "--ray-connect-timeout", "3"], env=ENV,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    assert time.monotonic() - t0 < 60
    line = _error_line(r.stderr)
    assert line.startswith(f"so101-sim {command}: error: no Ray cluster answers at "
                           f"--ray-address 127.0.0.1:{port}"), line
    assert f"`ray start --head --port {port}`" in line and "Traceback" not in r.stderr
    assert not out.exists()


def test_the_connect_timeout_lasts_as_long_as_the_command(tmp_path: Path,
                                                          monkeypatch) -> None:
    """main() called from Python sets --ray-connect-timeout for its own command only: a later
    API call in the same process waits the default (or what the caller had set) again."""
    from so101_sim.cli import main
    from so101_sim.workers.ray_connect import CONNECT_TIMEOUT_ENV, connect_timeout

    port = _closed_port()
    argv = [*EVAL, "--out", str(tmp_path / "out"), "--backend", "ray", "--ray-address",
            f"127.0.0.1:{port}", "--ray-connect-timeout", "1"]
    monkeypatch.delenv(CONNECT_TIMEOUT_ENV, raising=False)
    assert main(argv) == 2
    assert CONNECT_TIMEOUT_ENV not in os.environ and connect_timeout() == 30.0
    monkeypatch.setenv(CONNECT_TIMEOUT_ENV, "7")
    assert main(argv) == 2
    assert os.environ[CONNECT_TIMEOUT_ENV] == "7"


def test_a_port_that_never_answers_is_bounded(tmp_path: Path, silent_port: int) -> None:
    out = tmp_path / "out"
    t0 = time.monotonic()
    r = subprocess.run([EXE, *EVAL, "--out", str(out), "--backend", "ray", "--ray-address",
                        f"127.0.0.1:{silent_port}", "--ray-connect-timeout", "5"], env=ENV,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert time.monotonic() - t0 < 120
    line = _error_line(r.stderr)
    assert f"Ray did not connect to 127.0.0.1:{silent_port} within 5 s" in line, line
    assert f"ray start --head --port {silent_port}" in line and "Traceback" not in r.stderr
    assert not out.exists()  # eval_config.json was written, then removed with its folder


def _signal_when(proc: subprocess.Popen, ready: Path, sig: signal.Signals) -> float:
    """Send `sig` once `ready` exists; return the seconds the process took to end."""
    deadline = time.monotonic() + 300
    while not (ready.is_file() and ready.stat().st_size) and proc.poll() is None:
        assert time.monotonic() < deadline, "the run never got there"
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[1][-2000:]
    time.sleep(1.0)
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"{sig.name} did not end the run within 60 s")
    return time.monotonic() - t0


def _ray_processes() -> int:
    out = subprocess.run(["ps", "-eo", "cmd"], capture_output=True, text=True).stdout
    return sum(("ray::" in ln or "raylet" in ln or "gcs_server" in ln)
               for ln in out.splitlines())


# Stands in for a signal that lands inside `import ray` (SIGTERM's handler raises SystemExit(15)
# at whatever line runs, Ctrl-C raises KeyboardInterrupt): raised by the import system when
# `ray/__init__.py` reaches CUT, after `ray._private.worker` has registered its exit hook.
_CUT_IMPORT = """
import sys
cut, exc = sys.argv[1], {"SystemExit": SystemExit(15), "KeyboardInterrupt": KeyboardInterrupt()}
fired = []
class Cut:  # once: the failed `ray` leaves sys.modules, and Ray's exit hook imports it anew
    def find_spec(self, name, path=None, target=None):
        if name == cut and not fired:
            fired.append(name)
            raise exc[sys.argv[2]]
sys.meta_path.insert(0, Cut())
from so101_sim.workers.ray_pool import import_ray
try:
    import_ray()
except KeyboardInterrupt:
    sys.exit(130)  # as the CLI ends on Ctrl-C
"""


@pytest.mark.parametrize(("cut", "exc"), [("ray.internal", "SystemExit"),
                                          ("ray.client_builder", "KeyboardInterrupt")])
def test_a_signal_inside_import_ray_ends_without_a_traceback(cut: str, exc: str) -> None:
    """CI once printed Ray's exit hook failing on the half-imported package (``module 'ray' has
    no attribute 'actor'``, which this reproduces without the fix)."""
    r = subprocess.run([sys.executable, "-c", _CUT_IMPORT, cut, exc], env=ENV,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == (15 if exc == "SystemExit" else 130), r.stderr[-2000:]
    assert "atexit" not in r.stderr and "has no attribute" not in r.stderr, r.stderr[-2000:]


# A signal inside `ray._private.worker` itself, after its exit hook is registered: that
# module then leaves sys.modules too, and the hook can only be found among live objects.
_CUT_IN_WORKER = """
import atexit, sys
def shutdown(**kwargs):
    print("ray's exit hook ran")
shutdown.__module__ = "ray._private.worker"
atexit.register(shutdown, _exiting_interpreter=True)
assert "ray._private.worker" not in sys.modules
from so101_sim.workers.ray_pool import forget_ray_shutdown
forget_ray_shutdown()
"""


def test_a_signal_inside_rays_worker_module_unregisters_its_exit_hook() -> None:
    """CI once printed ``partially initialized module 'ray' has no attribute '_private'``
    from Ray's exit hook after a Ctrl-C inside `import ray`."""
    r = subprocess.run([sys.executable, "-c", _CUT_IN_WORKER], env=ENV, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "exit hook ran" not in r.stdout
    keep = _CUT_IN_WORKER.replace("forget_ray_shutdown()\n", "")  # the control: it runs
    r = subprocess.run([sys.executable, "-c", keep], env=ENV, capture_output=True, text=True,
                       timeout=120)
    assert "ray's exit hook ran" in r.stdout


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signals_end_a_run_that_is_connecting(tmp_path: Path, silent_port: int,
                                              sig: signal.Signals) -> None:
    out = tmp_path / "out"
    proc = subprocess.Popen([EXE, *EVAL, "--out", str(out), "--backend", "ray",
                             "--ray-address", f"127.0.0.1:{silent_port}",
                             "--ray-connect-timeout", "120"], env=ENV, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    took = _signal_when(proc, out / "eval_config.json", sig)
    err = proc.communicate()[1]
    assert took < 15 and "Traceback" not in err, err[-2000:]
    assert proc.returncode == (130 if sig == signal.SIGINT else sig.value)
    assert not out.exists()


@pytest.mark.parametrize(("sig", "stage"), [(signal.SIGINT, "starting"),
                                            (signal.SIGTERM, "running")])
def test_signals_end_a_run_on_a_local_runtime(tmp_path: Path, sig: signal.Signals,
                                              stage: str) -> None:
    """While the local Ray runtime starts (the signal waits until it has started, then the
    runtime is shut down) and while episodes run: the run ends, no Ray process stays."""
    before, out = _ray_processes(), tmp_path / "out"
    # "running": 64 episodes, so the signal (1 s after the first one ends) lands mid-run; with
    # 8, a loaded CI machine sometimes finished them all first and the signal met the shutdown
    argv = [*EVAL[:3], "--episodes", "64" if stage == "running" else "8", *EVAL[5:]]
    proc = subprocess.Popen([EXE, *argv, "--out", str(out), "--backend", "ray"], env=ENV,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    ready = out / ("eval_config.json" if stage == "starting" else "episodes.jsonl")
    took = _signal_when(proc, ready, sig)
    err = proc.communicate()[1]
    assert took < 30 and "Traceback" not in err, err[-2000:]
    assert proc.returncode == (130 if sig == signal.SIGINT else sig.value), err[-2000:]
    if stage == "starting":
        assert not out.exists()
    else:  # finished episodes are kept for --resume, and the run was cut short
        assert 1 <= (out / "episodes.jsonl").read_text().count("\n") < 64
    deadline = time.monotonic() + 30
    while _ray_processes() > before and time.monotonic() < deadline:
        time.sleep(1)
    assert _ray_processes() <= before


# SIGTERM while the main thread waits inside one long ray.wait (in C++): Ray's signal check
# there catches the handler's SystemExit(15) and raises SystemExit(1) instead (CI saw rc 1).
SIGTERM_IN_RAY_WAIT = """
import os, signal, sys, threading, time
import ray
from so101_sim.workers.ray_connect import init_holding_signals, signal_exit_code
init_holding_signals(lambda: ray.init(address="local", num_cpus=1, include_dashboard=False,
                                      log_to_driver=False))
ref = ray.remote(lambda: time.sleep(60)).remote()
threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGTERM)).start()
try:
    if sys.argv[1] == "kept":
        with signal_exit_code():
            ray.wait([ref], timeout=30)
    else:
        ray.wait([ref], timeout=30)
    print("the wait was not interrupted", file=sys.stderr)
finally:
    ray.shutdown()
"""


@pytest.mark.parametrize("mode", ["ray", "kept"])
def test_sigterm_inside_a_ray_wait_exits_15(mode: str) -> None:
    r = subprocess.run([sys.executable, "-c", SIGTERM_IN_RAY_WAIT, mode], env=ENV,
                       capture_output=True, text=True, timeout=180)
    assert "not interrupted" not in r.stderr and "Traceback" not in r.stderr, r.stderr[-2000:]
    # "ray": Ray's own exit code, which `signal_exit_code` (the CLI wraps every command in
    # it) exists to correct; if Ray ever keeps 15 itself, the wrapper can go
    assert r.returncode == (1 if mode == "ray" else 15), r.stderr[-2000:]

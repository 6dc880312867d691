"""The worker seam (so101_sim.workers) with a trivial service: replies, errors, a worker that
dies, and the backend checks. The Ray backend runs the same checks in test_ray_backend.py."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import so101_sim
from so101_sim.workers import check_backend, start_pool


class Counter:
    """A service: counts calls, can raise, can report its pid, can die."""

    def __init__(self, start: int = 0) -> None:
        self.n = start

    def add(self, k: int) -> int:
        self.n += k
        return self.n

    def fail(self) -> None:
        raise ValueError("asked to fail")

    def pid(self) -> int:
        return os.getpid()

    def sleep(self, s: float) -> float:
        time.sleep(s)
        return s


class CounterFactory:
    def __init__(self, start: int = 0) -> None:
        self.start = start

    def __call__(self) -> Counter:
        return Counter(self.start)


class BrokenFactory:
    def __call__(self) -> Counter:
        raise OSError("no GL here")


def check_pool_contract(pool) -> None:
    """What every backend must do; shared with the Ray tests."""
    assert pool.size == 2
    for k in (1, 2, 3):  # calls on one worker are answered in order
        pool.submit(0, "add", k)
    pool.submit(1, "fail")
    assert pool.pending(0) == 3 and pool.busy == 4
    assert pool.least_busy() == 1
    replies = pool.collect(wait_all=True)
    assert pool.busy == 0
    values = [r.value for r in replies if r.worker == 0]
    assert values == [11, 13, 16]
    (err,) = [r for r in replies if r.worker == 1]
    assert err.failed and "ValueError: asked to fail" in err.error and err.died is None
    pool.submit(1, "add", 5)  # still usable after an error
    (r,) = pool.collect()
    assert r.value == 15 and r.args == (5,) and r.method == "add"


def test_local_pool_contract() -> None:
    with start_pool(CounterFactory(10), 2, name="test-counter") as pool:
        check_pool_contract(pool)
        assert pool.info().to_dict()["backend"] == "local"


def test_local_pool_replaces_a_dead_worker() -> None:
    with start_pool(CounterFactory(), 2, name="test-counter") as pool:
        pool.submit(0, "pid")
        (r,) = pool.collect()
        pool.submit(0, "sleep", 30.0)
        pool.submit(0, "add", 1)  # queued behind the sleep: lost with the worker too
        os.kill(r.value, signal.SIGKILL)
        replies = pool.collect(wait_all=True)
        assert [(x.method, bool(x.died)) for x in replies] == [("sleep", True), ("add", True)]
        assert "died" in replies[0].died
        pool.submit(0, "add", 2)  # the replacement is a fresh service
        assert pool.collect()[0].value == 2
        assert pool.info().restarts == 1


def test_local_pool_hung_worker_times_out() -> None:
    with start_pool(CounterFactory(), 1, name="test-counter", timeout_s=1.0) as pool:
        pool.submit(0, "sleep", 60.0)
        t = time.monotonic()
        (r,) = pool.collect()
        assert r.died and "no reply within 1 s" in r.died and time.monotonic() - t < 30


def test_local_pool_start_failure_is_named() -> None:
    with pytest.raises(RuntimeError, match=r"could not start its BrokenFactory.*no GL here"):
        start_pool(BrokenFactory(), 1, name="test-broken")


def test_backend_arguments_are_checked() -> None:
    with pytest.raises(ValueError, match=r"backend='slurm' is not known; expected one of"):
        check_backend("slurm", None)
    with pytest.raises(ValueError, match="--ray-address auto only applies with --backend ray"):
        check_backend("local", "auto")


def test_without_ray_backend_ray_says_how_to_install(tmp_path) -> None:
    code = ("import sys; sys.modules['ray'] = None\n"
            "from so101_sim.cli import main\n"
            f"sys.exit(main(['eval', '--policy', 'expert', '--episodes', '1', '--out', "
            f"{str(tmp_path / 'run')!r}, '--backend', 'ray']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2, out.stderr[-2000:]
    assert "--backend ray needs Ray, which is not installed" in out.stderr
    assert "pip install 'so101-sim[ray]'" in out.stderr


def test_import_so101_sim_loads_no_ray_or_torch() -> None:
    code = ("import sys, so101_sim, so101_sim.workers, so101_sim.record.api, so101_sim.harness; "
            "print(sorted(m for m in ('ray', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=300).stdout
    assert out.strip() == "[]"


SLOW_EXIT = """
import atexit, time
atexit.register(time.sleep, 60)  # a teardown that would hold the command's output open
"""

SERVER_PROBE = """
import gc, sys

class Probe:
    def probe(self):
        return {"frozen": gc.get_freeze_count(),
                "server_init": "so101_sim.workers.server_init" in sys.modules,
                "slow_exit": "slow_exit" in sys.modules}

class ProbeFactory:
    def __call__(self):
        return Probe()
"""

DRIVER = """
import json, sys
sys.path.insert(0, sys.argv[1])
from so101_sim.workers import start_pool
from server_probe import ProbeFactory

with start_pool(ProbeFactory(), 1, name="test-exit", preload=("slow_exit",)) as pool:
    pool.submit(0, "probe")
    (reply,) = pool.collect()
print(json.dumps(reply.value), flush=True)
"""


def test_the_fork_server_leaves_without_holding_the_commands_output(tmp_path) -> None:
    """The fork server keeps the driver's stdout and stderr, so a reader of them (a pipe,
    subprocess.run, CI) waits until the server is gone: it exits at once, skipping its
    interpreter's teardown (here an exit handler that would sleep 60 s), and the objects its
    preloads made are frozen for its workers."""
    (tmp_path / "slow_exit.py").write_text(SLOW_EXIT)
    (tmp_path / "server_probe.py").write_text(SERVER_PROBE)
    # the server finds both on the driver's sys.path (the cwd is elsewhere)
    out = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path)], capture_output=True,
                         text=True, timeout=45, cwd=tmp_path.parent)  # closed long before the sleep
    assert out.returncode == 0, out.stderr[-3000:]
    probe = json.loads(out.stdout.strip().splitlines()[-1])
    assert probe["server_init"] is True and probe["slow_exit"] is True  # both preloaded
    assert probe["frozen"] > 1000  # the preloads' objects (so101_sim, numpy, ...) are frozen


PATH_PROBE = """
import os, sys

class PathProbe:
    def probe(self):
        return {"so101_sim": os.path.dirname(sys.modules["so101_sim"].__file__),
                "stray": "stray_module" in sys.modules}

class PathProbeFactory:
    def __call__(self):
        return PathProbe()
"""

PATH_DRIVER = """
import json, os, sys
sys.path.insert(0, os.environ["PROBE_DIR"])  # a path the driver adds at run time
import so101_sim
from so101_sim.workers import start_pool
from path_probe import PathProbeFactory

if __name__ == "__main__":
    with start_pool(PathProbeFactory(), 1, name="test-path", preload=("stray_module",)) as pool:
        pool.submit(0, "probe")
        (reply,) = pool.collect()
    here = {"so101_sim": os.path.dirname(so101_sim.__file__),
            "stray": "stray_module" in sys.modules}
    print(json.dumps({"worker": reply.value, "driver": here}), flush=True)
"""


def test_workers_import_what_the_driver_imports_not_the_current_directory(tmp_path) -> None:
    """A command run from inside another checkout (its own so101_sim/ in the cwd): Python
    3.12's fork server put the cwd first on its sys.path, so its preloads came from there and
    the workers mixed that checkout's modules with the driver's (here: they could not start).
    The server imports from the driver's sys.path: the cwd's modules are not found, and a path
    the driver added at run time is."""
    probe_dir, cwd = tmp_path / "probe", tmp_path / "checkout"
    (cwd / "so101_sim").mkdir(parents=True)
    (cwd / "so101_sim" / "__init__.py").write_text("")  # another version, say
    (cwd / "stray_module.py").write_text("")
    probe_dir.mkdir()
    (probe_dir / "path_probe.py").write_text(PATH_PROBE)
    (probe_dir / "driver.py").write_text(PATH_DRIVER)  # a script: its dir, not the cwd, leads
    out = subprocess.run([sys.executable, str(probe_dir / "driver.py")], capture_output=True,
                         text=True, timeout=120, cwd=cwd,
                         env={**os.environ, "PROBE_DIR": str(probe_dir)})
    assert out.returncode == 0, out.stderr[-3000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["driver"] == {"so101_sim": str(Path(so101_sim.__file__).parent), "stray": False}
    assert seen["worker"] == seen["driver"]  # the same so101_sim, no stray module


HEAVY_DEP = """
import os
with open(os.environ["IMPORT_LOG"], "a") as f:  # one line per process that imports this
    f.write(f"{os.getpid()}\\n")
"""

PROBE_CLI = """
import json, os, sys
import heavy_dep  # what torch and lerobot are to lerobot-eval's module

class PidProbe:
    def pid(self):
        return os.getpid()

class PidProbeFactory:
    def __call__(self):
        return PidProbe()

def main():
    from so101_sim.workers import start_pool
    with start_pool(PidProbeFactory(), 3, name="test-script", preload=()) as pool:
        for i in range(3):
            pool.submit(i, "pid")
        replies = []
        while len(replies) < 3:
            replies += pool.collect()
        pids = sorted(r.value for r in replies)
    print(json.dumps({"driver": os.getpid(), "workers": pids}), flush=True)

if __name__ == "__main__":
    main()
"""

CONSOLE_SCRIPT = """
import sys
from probe_cli import main
if __name__ == "__main__":
    sys.exit(main())
"""


@pytest.mark.parametrize("how", ["console script", "python -m"])
def test_workers_do_not_import_the_commands_module_again(tmp_path, how) -> None:
    """Each forked worker runs the command's main module again first; Python 3.12's fork
    server never imports it for them, so every one of lerobot-eval's 16 env workers imported
    torch and lerobot itself (28-34 s of its 121-124 s on 100 episodes). The server imports
    the command's module once, and the workers find its imports done."""
    for name, text in (("heavy_dep.py", HEAVY_DEP), ("probe_cli.py", PROBE_CLI),
                       ("entry.py", CONSOLE_SCRIPT)):
        (tmp_path / name).write_text(text)
    log = tmp_path / "imports.log"
    cmd = ([sys.executable, str(tmp_path / "entry.py")] if how == "console script"
           else [sys.executable, "-m", "probe_cli"])
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env={**os.environ, "IMPORT_LOG": str(log), "PYTHONPATH": str(tmp_path)})
    assert out.returncode == 0, out.stderr[-3000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    importers = [int(p) for p in log.read_text().split()]
    assert len(seen["workers"]) == 3 and seen["driver"] in importers
    assert not set(seen["workers"]) & set(importers)  # no worker imported it itself
    assert len(importers) == 2  # the driver and the fork server, once each


STDIN_SERVICE = """
class Echo:
    def echo(self, x):
        return x

class EchoFactory:
    def __call__(self):
        return Echo()
"""

STDIN_SCRIPT = """
from stdin_service import EchoFactory
from so101_sim.workers import start_pool
with start_pool(EchoFactory(), 2, name="test-stdin") as pool:
    pool.submit(0, "echo", 1)
    print(pool.collect()[0].value)
"""


def test_a_script_read_from_stdin_is_refused_in_one_line(tmp_path) -> None:
    """`python - <<EOF` names its __main__ '<stdin>', which each forkserver worker ran again
    from the cwd: every worker died on FileNotFoundError under its own traceback, and the pool
    said only "exited with code None while starting". Now one line says why and what works."""
    (tmp_path / "stdin_service.py").write_text(STDIN_SERVICE)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run([sys.executable, "-"], input=STDIN_SCRIPT, capture_output=True,
                         text=True, timeout=120, cwd=tmp_path, env=env)
    assert out.returncode == 1
    assert out.stderr.strip().splitlines()[-1] == (
        "RuntimeError: so101_sim's env workers start with multiprocessing's forkserver, which "
        f"runs this program's __main__ again from its file, and '{tmp_path / '<stdin>'}' is "
        "not a file (a script read from stdin, as `python - <<EOF` does): save the script and "
        "run `python script.py`, or pass it with `python -c`")
    assert "FileNotFoundError" not in out.stderr  # no worker was started
    fixed = subprocess.run([sys.executable, "-c", STDIN_SCRIPT], capture_output=True,
                           text=True, timeout=120, cwd=tmp_path, env=env)
    assert fixed.returncode == 0 and fixed.stdout.split() == ["1"], fixed.stderr[-2000:]

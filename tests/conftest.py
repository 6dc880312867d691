"""Shared fixtures. Nothing in the tests may download: the hub is switched off."""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
# A test run started in the background without job control (`nohup make test &`) inherits an
# ignored SIGINT and passes it to every child, so the tests that stop a run with Ctrl-C would
# hang: give the children the default (a Python child then raises KeyboardInterrupt).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
# Sleeping OpenMP waits: spinning torch threads slow down 10x+ when env workers share the cores.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

from so101_sim.sim import PickPlaceEnv

REST = np.array([-10.374, -81.670, 77.846, 2.681, 123.209, 6.495], dtype=np.float32)
SMALL = (48, 64)


@pytest.fixture
def pixel_env():
    env = PickPlaceEnv(image_size=SMALL, obs_type="pixels_agent_pos_env_state",
                       render_mode="rgb_array")
    yield env
    env.close()


@pytest.fixture
def state_env():
    env = PickPlaceEnv(obs_type="state")
    yield env
    env.close()


@pytest.fixture
def child_tmpdir(monkeypatch):
    """A TMPDIR for the child processes a test starts, whose temporary files would stay in
    /tmp: what a killed or ``os._exit``-ing process had in flight (multiprocessing's pymp-*
    folder) and what lerobot never removes (a tmp*.json per policy config it parses) go with
    this folder. Set in os.environ for children that copy it; this process's own tempfile
    folder is looked up first, so it stays where it was. Short, since a fork server's socket
    path inside it must stay under 108 bytes."""
    tempfile.gettempdir()  # cached now: only children see the new TMPDIR
    path = tempfile.mkdtemp(prefix="so101-child-")
    monkeypatch.setenv("TMPDIR", path)
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def lerobot_tempfiles(monkeypatch, tmp_path):
    """This process's tempfile folder is the test's tmp_path: lerobot's
    ``PreTrainedConfig.from_pretrained`` (``DiffusionPolicy.from_pretrained`` in a test) copies
    each config it parses to a tmp*.json it never removes."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))


@pytest.fixture
def lose_a_ctrl_c(monkeypatch):
    """A function that sends this process SIGINT while a weakref callback runs, where Python
    prints and drops the handler's KeyboardInterrupt (as during garbage collection); it
    asserts the interrupt was dropped and returns how many have been so far."""
    import sys
    import weakref

    dropped: list[type] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: dropped.append(u.exc_type)
                        if u.exc_type is KeyboardInterrupt else None)  # not another __del__'s

    class Thing:
        pass

    def callback(_ref: object) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        sum(range(1000))  # the handler runs here, inside the callback

    def lose() -> int:
        before = len(dropped)
        thing = Thing()
        keep = weakref.ref(thing, callback)
        del thing  # the callback runs now
        assert keep() is None and dropped[before:] == [KeyboardInterrupt]
        return len(dropped)

    return lose


# Seconds each module took in one `make test` (2026-12-06, 2 workers, 2034 s in all, run with
# --durations=0). Only the order of the work depends on them: the longest units start first,
# so the two workers end together (longest-first scheduling). A module not listed (each of
# those took under 10 s) runs after these.
MODULE_SECONDS = {
    "test_shipped_policy": 204, "test_recording": 175, "test_ray_backend": 165,
    "test_lerobot_robot": 157, "test_ray_cluster": 116, "test_full_disk": 105,
    "test_durability": 103, "test_training": 92, "test_gpu_scripts": 87, "test_save_rollouts": 75,
    "test_against": 70, "test_lerobot_zero_flags": 61, "test_exact_speedups": 60,
    "test_ray_unreachable": 51, "test_locks": 50, "test_startup": 44, "test_policy_classes": 35,
    "test_explain": 32, "test_bad_input": 31, "test_bench_scripts": 28, "test_harness": 28,
    "test_grasp_trace": 28, "test_testing": 25, "test_lerobot_train_env": 23, "test_wrist": 22,
    "test_augment": 18, "test_baselines": 16, "test_packaging": 14, "test_sequential": 12,
    "test_docs": 12, "test_probe_cube": 12,
}


def work_unit(nodeid: str) -> str:
    """What one xdist worker runs as a whole: a test module, so its module-scoped fixtures
    are built once; and every Ray module together ("ray"), since a second local Ray runtime
    on this machine would join the first instead of starting its own."""
    path = nodeid.split("::", 1)[0]
    return "ray" if Path(path).name.startswith("test_ray_") else path


def _unit_seconds() -> dict[str, float]:
    seconds: dict[str, float] = {}
    for module, s in MODULE_SECONDS.items():
        unit = work_unit(f"tests/{module}.py")
        seconds[unit] = seconds.get(unit, 0) + s
    return seconds


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Longest work units first, each unit's tests together and in file order."""
    seconds = _unit_seconds()
    units = {item.nodeid: work_unit(item.nodeid) for item in items}
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        first.setdefault(units[item.nodeid], i)
    items.sort(key=lambda it: (-seconds.get(units[it.nodeid], 0), first[units[it.nodeid]]))


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, when installed
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """`--dist loadscope` (what `make test` runs) hands out `work_unit`s, in collection order."""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ByWorkUnit(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return work_unit(nodeid)

    config.option.loadscopereorder = False  # keep the longest-first order above
    return ByWorkUnit(config, log)

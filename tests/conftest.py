"""Shared fixtures. Nothing in the tests may download: the hub is switched off."""

from __future__ import annotations

import os
import signal

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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Keep every Ray test on one xdist worker (`make test` runs `--dist loadgroup`): a second
    local Ray runtime on this machine would join the first instead of starting its own."""
    for item in items:
        if item.path.name.startswith("test_ray_"):
            item.add_marker(pytest.mark.xdist_group("ray"))

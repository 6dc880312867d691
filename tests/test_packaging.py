"""The wheel carries the data folders and the env runs from a non-editable install."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import imageio.v3 as iio
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_installs_and_env_runs_from_it(tmp_path):
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "--quiet", "-w", str(dist), str(ROOT)], check=True)
    wheel = next(dist.glob("so101_sim-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for required in ("so101_sim/assets/so101.xml", "so101_sim/assets/scene_pick_place.xml",
                     "so101_sim/envs/pick_place.toml", "so101_sim/env.py"):
        assert required in names, f"{required} missing from {wheel.name}"
    assert any(n.startswith("so101_sim/policy/") for n in names)

    # A fresh venv that sees this venv's packages (a plain path entry, so this venv's editable
    # so101_sim hook is not loaded) and gets so101_sim only from the wheel.
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          capture_output=True, text=True, check=True).stdout.strip()
    Path(site, "_test_deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    subprocess.run([py, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheel)],
                   check=True)
    code = ("import so101_sim, gymnasium as gym\n"
            "print(so101_sim.__file__)\n"
            "env = gym.make(so101_sim.ENV_ID, image_size=(48, 64))\n"
            "obs, _ = env.reset(seed=0); env.step(obs['agent_pos'])\n"
            "print(env.unwrapped.visuals, obs['pixels']['front'].shape)\n")
    out = subprocess.run([py, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert out[0].startswith(str(venv)), f"so101_sim imported from {out[0]}, not the wheel"
    assert out[1] == "mesh (48, 64, 3)"

    # The console script from the wheel runs the demo.
    demo = tmp_path / "demo"
    subprocess.run([venv / "bin" / "so101-sim", "demo", "--steps", "10", "--image-size",
                    "48x64", "--out", str(demo)], cwd=tmp_path, check=True, capture_output=True)
    assert (demo / "demo.mp4").stat().st_size > 0


def test_demo_writes_video_and_one_png_per_camera(tmp_path):
    from so101_sim.cli import main

    assert main(["demo", "--steps", "30", "--image-size", "96x128", "--out", str(tmp_path)]) == 0
    frames = iio.imread(tmp_path / "demo.mp4", plugin="pyav")
    assert frames.shape == (31, 96, 256, 3)  # reset frame + 30 steps, front|side
    for cam in ("front", "side"):
        img = iio.imread(tmp_path / f"{cam}.png")
        assert img.shape == (96, 128, 3) and img.std() > 5


@pytest.mark.parametrize("task", ["pick_place", "pick_place_dr", "tidy"])
def test_demos_scene_opens_in_plain_mujoco_at_the_seeds_start(task, tmp_path, capsys):
    """assets/scene_pick_place.xml names STL files that live elsewhere and lacks what each
    task adds, so plain MuJoCo could not open a task's scene ("Error opening file
    'assets/base_motor_holder_so101_v1.stl'"). The demo writes scene.xml: the same bodies,
    geoms and meshes as the env's model, and keyframe seed_N puts every body where the env's
    reset put it (to the 6 digits MuJoCo's writer keeps)."""
    import gymnasium as gym
    import mujoco
    import numpy as np

    from so101_sim.cli import main

    out = tmp_path / "demo"
    assert main(["demo", "--steps", "2", "--image-size", "48x64", "--seed", "3", "--task", task,
                 "--out", str(out)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"open the scene in MuJoCo's viewer: python -m mujoco.viewer --mjcf={out}/scene.xml "
        "(keyframe seed_3: the rollout's start)")
    m = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    env = gym.make("so101_sim/PickPlace-v0", task=task, obs_type="state", mesh_width=64)
    env.reset(seed=3)
    e = env.unwrapped
    assert (m.nbody, m.ngeom, m.nmesh, m.nmeshface, m.nu, m.nmocap) == (
        e.model.nbody, e.model.ngeom, e.model.nmesh, e.model.nmeshface, e.model.nu,
        e.model.nmocap)
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("seed_3").id)
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(d.xpos, e.data.xpos, atol=2e-6)
    np.testing.assert_allclose(d.ctrl, e.data.ctrl, atol=1e-4)
    env.close()


def test_demo_refuses_steps_with_grid(tmp_path, capsys):
    from so101_sim.cli import main

    assert main(["demo", "--grid", "2x2", "--steps", "30", "--out", str(tmp_path / "d")]) == 2
    assert "--steps 30 given with --grid" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_cli_rejects_bad_image_size(capsys):
    from so101_sim.cli import main

    try:
        main(["demo", "--image-size", "480by640"])
    except SystemExit as exc:
        assert exc.code == 2
    assert "expected HEIGHTxWIDTH" in capsys.readouterr().err


def test_import_does_not_load_torch():
    code = "import sys, so101_sim, so101_sim.sim.env; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_version_names_the_package_and_what_results_depend_on(capsys):
    """`so101-sim --version`: the installed distribution's version (one source with
    `so101_sim.__version__`) and MuJoCo's, lerobot's, torch's, Gymnasium's, for a bug report."""
    from importlib import metadata

    import so101_sim
    from so101_sim.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    line = capsys.readouterr().out.strip()
    assert so101_sim.__version__ == metadata.version("so101-sim")
    assert line.startswith(f"so101-sim {so101_sim.__version__} (")
    for dist in ("mujoco", "lerobot", "torch", "gymnasium"):
        assert f"{dist} {metadata.version(dist)}" in line
    # `python -m so101_sim` is the same command
    run = subprocess.run([sys.executable, "-m", "so101_sim", "--version"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == line, run.stderr[-2000:]

"""Roll the env with a fixed joint-space action sequence and save what the cameras saw; or,
with a grid, one contact sheet of many seeds' first frames (what a task's randomization spans).
"""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from tqdm import tqdm

from so101_sim.sim.env import IMAGE_SIZE, PickPlaceEnv
from so101_sim.sim.scene import mesh_grid_for, scene_xml
from so101_sim.tasks import DEFAULT_TASK
from so101_sim.utils.mp4 import H264Writer
from so101_sim.utils.paths import foreign_folder

# Joint-space waypoints (LeRobot units) visited in order: reach out over the table, sweep
# across the workspace opening and closing the gripper, and return to rest.
_WAYPOINTS = np.array([
    [-10.374, -81.670, 77.846, 2.681, 123.209, 6.495],  # rest pose
    [0.0, -20.0, 30.0, 70.0, 0.0, 60.0],
    [-30.0, 10.0, 15.0, 65.0, -10.0, 60.0],
    [-30.0, 10.0, 15.0, 65.0, -10.0, 5.0],
    [30.0, 0.0, 0.0, 85.0, 50.0, 5.0],
    [30.0, 0.0, 0.0, 85.0, 50.0, 60.0],
    [-10.374, -81.670, 77.846, 2.681, 123.209, 6.495],
])


def fixed_action_sequence(n_steps: int) -> np.ndarray:
    """(n_steps, 6) float32 actions interpolating smoothly through the waypoints."""
    s = np.linspace(0.0, len(_WAYPOINTS) - 1, n_steps)
    i = np.minimum(s.astype(int), len(_WAYPOINTS) - 2)
    t = s - i
    t = t * t * (3 - 2 * t)  # ease in/out so the servos are not slammed
    seq = _WAYPOINTS[i] + t[:, None] * (_WAYPOINTS[i + 1] - _WAYPOINTS[i])
    return seq.astype(np.float32)


def _make_folder(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out {out_dir} is a file; expected a folder for the demo's video "
                         "and images: choose another --out")
    if (what := foreign_folder(out_dir)) is not None:
        raise ValueError(f"--out {out_dir} {what}; the demo's video and images would go among "
                         "its files: choose another --out")
    out_dir.mkdir(parents=True, exist_ok=True)


def run_demo(out_dir: Path, steps: int = 240, image_size: tuple[int, int] = IMAGE_SIZE,
             seed: int = 0, task: str = DEFAULT_TASK) -> dict[str, Path]:
    """Write demo.mp4 (front|side), one PNG per camera (the last frame) and scene.xml (the
    scene for plain MuJoCo, the seed's start as keyframe ``seed_N``) into `out_dir`."""
    _make_folder(out_dir)
    env = PickPlaceEnv(task=task, image_size=image_size, render_mode="rgb_array")
    obs, _ = env.reset(seed=seed)
    scene = out_dir / "scene.xml"
    scene.write_text(scene_xml(env.task, mesh_grid_for(env.task, image_size[1]), env.data,
                               key=f"seed_{seed}"))
    video_path = out_dir / "demo.mp4"
    with H264Writer(video_path, fps=env.task.fps) as writer:
        writer.append(env.render())
        for action in tqdm(fixed_action_sequence(steps), desc="demo", unit="step"):
            obs, _, terminated, truncated, _ = env.step(action)
            writer.append(env.render())
            if terminated or truncated:
                break
    paths = {"video": video_path, "scene": scene}
    for cam in env.cameras:
        paths[cam] = out_dir / f"{cam}.png"
        imageio.imwrite(paths[cam], obs["pixels"][cam])
    env.close()
    return paths


def parse_grid(text: str) -> tuple[int, int]:
    """"4x4" -> (rows, columns)."""
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        rows = cols = 0
    if not (1 <= rows <= 16 and 1 <= cols <= 16):
        raise ValueError(f"grid {text!r} is invalid; expected ROWSxCOLUMNS with 1..16 each, "
                         "e.g. 4x4")
    return rows, cols


def contact_sheet(out_dir: Path, task: str = "pick_place_dr", grid: tuple[int, int] = (4, 4),
                  seed: int = 0, image_size: tuple[int, int] = (240, 320),
                  camera: str = "front") -> Path:
    """Write contact_sheet.png: the first `camera` frame of seeds seed.. seed+rows*cols-1,
    row by row, each labelled with its seed; returns its path."""
    from PIL import Image, ImageDraw

    rows, cols = grid
    _make_folder(out_dir)
    env = PickPlaceEnv(task=task, image_size=image_size, cameras=(camera,))
    h, w = image_size
    sheet = Image.new("RGB", (cols * w, rows * h))
    for i in tqdm(range(rows * cols), desc="contact sheet", unit="seed"):
        obs, _ = env.reset(seed=seed + i)
        tile = Image.fromarray(obs["pixels"][camera])
        ImageDraw.Draw(tile).text((4, 2), f"seed {seed + i}", fill=(255, 255, 255))
        sheet.paste(tile, ((i % cols) * w, (i // cols) * h))
    env.close()
    path = out_dir / f"contact_sheet_{env.task.name}_{rows}x{cols}.png"
    sheet.save(path)
    return path

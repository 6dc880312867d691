"""Argument checks of the env: each error names the bad value, what was expected and how to
pass it instead."""

from __future__ import annotations

from typing import Any

import numpy as np

from so101_sim.tasks.spec import ALL_CAMERAS
from so101_sim.utils.units import MOTOR_NAMES


def check_action(action: Any) -> np.ndarray:
    """Return `action` as float64[6] or raise ValueError saying what was expected."""
    try:
        a = np.asarray(action)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"action {action!r} is not an array; expected float32[6] joint "
                         f"targets ({', '.join(MOTOR_NAMES)})") from exc
    if a.shape != (6,):
        raise ValueError(f"action has shape {a.shape}; expected (6,) joint targets in "
                         f"LeRobot units ({', '.join(MOTOR_NAMES)})")
    if a.dtype.kind != "f":
        raise ValueError(f"action has dtype {a.dtype}; expected a floating-point array "
                         "(float32), e.g. np.asarray(action, dtype=np.float32)")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action contains NaN or inf: {a.tolist()}; expected finite joint "
                         "targets (degrees, gripper 0..100)")
    return a.astype(np.float64)


def check_cameras(cameras: Any) -> tuple[str, ...]:
    """Camera names as a tuple, or a ValueError listing the valid ones."""
    names = (cameras,) if isinstance(cameras, str) else tuple(cameras)
    if not names or len(set(names)) != len(names) or any(c not in ALL_CAMERAS for c in names):
        raise ValueError(f"cameras={cameras!r} is invalid; expected distinct names from "
                         f"{ALL_CAMERAS}, e.g. ('front', 'side', 'wrist')")
    return names


def _pixels(value: Any) -> int | None:
    """`value` as an int in 16..2048 (an image side), else None."""
    try:
        ok = int(value) == value and not isinstance(value, (bool, str))
    except (TypeError, ValueError, OverflowError):  # None, "640", nan, inf
        return None
    return int(value) if ok and 16 <= value <= 2048 else None


def check_image_size(image_size: Any) -> tuple[int, int]:
    """(height, width) as ints in 16..2048, or a ValueError with an example."""
    try:
        h, w = (_pixels(v) for v in image_size)
    except (TypeError, ValueError):
        h = w = None
    if h is None or w is None:
        raise ValueError(f"image_size={image_size!r} is invalid; expected (height, width) "
                         "integers in 16..2048, e.g. (480, 640) or (96, 128)")
    return h, w


def check_mesh_width(mesh_width: Any) -> int:
    """An image width in 16..2048 whose mesh detail to use, or a ValueError."""
    width = _pixels(mesh_width)
    if width is None:
        raise ValueError(f"mesh_width={mesh_width!r} is invalid; expected the image width "
                         "whose mesh detail to use, an integer in 16..2048 (e.g. 640, the "
                         "recorded width), or None for image_size's")
    return width

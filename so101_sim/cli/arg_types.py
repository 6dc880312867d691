"""argparse types of the `so101-sim` flags: each refuses a bad value with what was expected."""

from __future__ import annotations

import argparse
from collections.abc import Callable

__all__ = ["eval_seed_int", "nonnegative_int", "parse_camera_map_arg", "parse_cameras",
           "parse_ensemble_coeff", "parse_image_size", "parse_steps", "positive_float",
           "positive_int", "unit_fraction"]


def parse_image_size(text: str) -> tuple[int, int]:
    """"480x640" -> (480, 640) (height x width)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"image size {text!r} is invalid; expected HEIGHTxWIDTH, e.g. 480x640") from None
    if not (16 <= h <= 2048 and 16 <= w <= 2048):
        raise argparse.ArgumentTypeError(f"image size {text!r} out of range; each side 16..2048")
    return h, w


def _int_from(low: int, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer; expected one >= {low}"
                                         ) from None
    if value < low:
        raise argparse.ArgumentTypeError(f"{value} is invalid; expected an integer >= {low}")
    return value


def positive_int(text: str) -> int:
    """argparse type for a count that must be >= 1 (steps, threads, rows per forward)."""
    return _int_from(1, text)


def nonnegative_int(text: str) -> int:
    """argparse type for a reset seed (>= 0, as Gymnasium requires) or a count that may be 0."""
    return _int_from(0, text)


def _float_where(text: str, ok: Callable[[float], bool], expected: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; expected {expected}"
                                         ) from None
    if not ok(value):  # nan fails every comparison, so it lands here too
        raise argparse.ArgumentTypeError(f"{text} is invalid; expected {expected}")
    return value


def positive_float(text: str) -> float:
    """argparse type for a duration in seconds: finite and > 0."""
    return _float_where(text, lambda v: 0 < v < float("inf"), "a finite number > 0")


def unit_fraction(text: str) -> float:
    """argparse type for a fraction in [0, 1] (e.g. how full a queue is)."""
    return _float_where(text, lambda v: 0 <= v <= 1, "a fraction in [0, 1]")


def eval_seed_int(text: str) -> int:
    """argparse type for the first seed of a curve: evaluation seeds only."""
    from so101_sim.dataset.schema import EVAL_SEED_START

    value = nonnegative_int(text)
    if value < EVAL_SEED_START:
        raise argparse.ArgumentTypeError(
            f"{value} is a training seed (demos use seeds below {EVAL_SEED_START}); a curve "
            f"measures on evaluation seeds, >= {EVAL_SEED_START}")
    return value


def parse_steps(text: str) -> list[int]:
    """`--steps 8000,12000` -> [8000, 12000]."""
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--steps {text!r}: expected checkpoint steps separated by commas, e.g. 8000,12000"
        ) from None


def parse_ensemble_coeff(text: str) -> float | str:
    """`--temporal-ensemble 0.01` -> 0.01; `off` -> "off" (chunk-wise)."""
    if text == "off":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--temporal-ensemble {text!r}: expected a coefficient such as 0.01, or 'off'"
        ) from None


def parse_cameras(text: str) -> tuple[str, ...]:
    """argparse type for --cameras: "front,side,wrist" -> ("front", "side", "wrist")."""
    from so101_sim.sim.env_args import check_cameras
    from so101_sim.tasks.spec import ALL_CAMERAS

    try:
        return check_cameras(tuple(c.strip() for c in text.split(",") if c.strip()))
    except ValueError:  # in the flag's own syntax, not the Python tuple check_cameras names
        raise argparse.ArgumentTypeError(f"{text!r} is invalid; expected distinct names from "
                                         f"{', '.join(ALL_CAMERAS)}, e.g. front,side") from None


def parse_camera_map_arg(text: str) -> dict[str, str]:
    """argparse type for --camera-map (see so101_sim.harness.camera_map)."""
    from so101_sim.harness.camera_map import parse_camera_map

    try:
        return parse_camera_map(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None

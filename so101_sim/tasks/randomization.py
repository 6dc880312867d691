"""The ``[randomize]`` section of a task file: which domain-randomization factors are on and
their ranges. Parsing only (no mujoco); ``so101_sim.sim.randomizer`` applies the draws.

Every key is optional and absent means "not randomized". Ranges are ``[low, high]`` and are
drawn uniformly; colours are ``[[r, g, b], [r, g, b]]`` (low and high per channel, 0..1).

=================  ===========================================================  ============
key                meaning                                                      kind
=================  ===========================================================  ============
light_azimuth      key light direction: compass angle (degrees)                 range
light_elevation    key light direction: angle above the table (degrees)         range
light_intensity    key light diffuse intensity (0..1, grey)                     range
ambient            headlight ambient level (0..1, grey)                         range
table_color        table base colour                                            colour range
cube_color         colour of the task's cube(s)                                 colour range
robot_color        colour of the robot's yellow printed parts                   colour range
table_texture      contrast of a procedural table pattern (0 = plain)           range
camera_position    offset of each camera along x, y and z (metres)              range
camera_rotation    rotation of each camera about a random axis (degrees)        range
camera_fovy        added to each camera's vertical field of view (degrees)      range
cube_size          cube edge length (metres; 0.015 .. 0.035)                    range
cube_mass          cube mass (kg)                                               range
cube_friction      cube sliding friction coefficient                            range
servo_gain         factor on every servo's position gain kp                     range
servo_damping      factor on every servo's damping (kv and joint damping)       range
distractors        number of distractor objects on the table ([min, max])       int range
=================  ===========================================================  ============
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from so101_sim.utils.text import did_you_mean

Range = tuple[float, float]
ColorRange = tuple[tuple[float, float, float], tuple[float, float, float]]

MAX_DISTRACTORS = 4  # bodies pre-built into a randomized scene (unused ones are hidden)

# key -> (value type, (lowest allowed, highest allowed), what it is for the error message)
_KEYS: dict[str, tuple[str, tuple[float, float], str]] = {
    "light_azimuth": ("range", (-360.0, 360.0), "degrees"),
    "light_elevation": ("range", (10.0, 90.0), "degrees above the table"),
    "light_intensity": ("range", (0.0, 1.0), "diffuse level"),
    "ambient": ("range", (0.0, 1.0), "ambient level"),
    "table_color": ("color", (0.0, 1.0), "RGB"),
    "cube_color": ("color", (0.0, 1.0), "RGB"),
    "robot_color": ("color", (0.0, 1.0), "RGB"),
    "table_texture": ("range", (0.0, 1.0), "pattern contrast"),
    "camera_position": ("range", (-0.1, 0.1), "metres"),
    "camera_rotation": ("range", (-20.0, 20.0), "degrees"),
    "camera_fovy": ("range", (-20.0, 20.0), "degrees"),
    "cube_size": ("range", (0.015, 0.035), "metres"),
    "cube_mass": ("range", (0.001, 0.5), "kg"),
    "cube_friction": ("range", (0.2, 3.0), "friction coefficient"),
    "servo_gain": ("range", (0.5, 1.5), "factor"),
    "servo_damping": ("range", (0.5, 2.0), "factor"),
    "distractors": ("int", (0, MAX_DISTRACTORS), "objects"),
}


@dataclass(frozen=True)
class Randomization:
    """Parsed ``[randomize]`` section; ``None`` fields are not randomized."""

    light_azimuth: Range | None = None
    light_elevation: Range | None = None
    light_intensity: Range | None = None
    ambient: Range | None = None
    table_color: ColorRange | None = None
    cube_color: ColorRange | None = None
    robot_color: ColorRange | None = None
    table_texture: Range | None = None
    camera_position: Range | None = None
    camera_rotation: Range | None = None
    camera_fovy: Range | None = None
    cube_size: Range | None = None
    cube_mass: Range | None = None
    cube_friction: Range | None = None
    servo_gain: Range | None = None
    servo_damping: Range | None = None
    distractors: tuple[int, int] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None}


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _parse_one(key: str, value: Any, source: str) -> Any:
    vtype, (lo, hi), unit = _KEYS[key]
    if vtype == "color":
        ok = (isinstance(value, list) and len(value) == 2
              and all(isinstance(c, list) and len(c) == 3 and all(map(_num, c)) for c in value))
        ok = ok and all(lo <= x <= hi for c in value for x in c)
        ok = ok and all(a <= b for a, b in zip(value[0], value[1], strict=True))
        if not ok:
            raise ValueError(f"{source}: randomize.{key} = {value!r} is invalid; expected "
                             "[[r, g, b], [r, g, b]] (low and high per channel, 0..1, low <= "
                             "high), e.g. [[0.3, 0.3, 0.3], [0.8, 0.8, 0.8]]")
        return tuple(tuple(float(x) for x in c) for c in value)
    ints = vtype == "int"
    ok = (isinstance(value, list) and len(value) == 2 and all(map(_num, value))
          and value[0] <= value[1] and lo <= value[0] and value[1] <= hi)
    if ok and ints:
        ok = all(isinstance(v, int) for v in value)
    if not ok:
        example = "[0, 3]" if ints else f"[{lo:g}, {hi:g}]"
        raise ValueError(f"{source}: randomize.{key} = {value!r} is invalid; expected "
                         f"[low, high] {'integers' if ints else 'numbers'} ({unit}) with "
                         f"{lo:g} <= low <= high <= {hi:g}, e.g. {example}")
    return (int(value[0]), int(value[1])) if ints else (float(value[0]), float(value[1]))


def parse_randomize(raw: dict[str, Any], source: str = "<dict>") -> Randomization:
    """Validate a ``[randomize]`` table; errors name the key, the value and what is allowed."""
    values = {}
    for key, value in raw.items():
        if key not in _KEYS:
            raise ValueError(f"{source}: unknown key 'randomize.{key}'"
                             f"{did_you_mean(key, _KEYS)}; allowed keys in [randomize]: "
                             f"{sorted(_KEYS)}")
        values[key] = _parse_one(key, value, source)
    return Randomization(**values)

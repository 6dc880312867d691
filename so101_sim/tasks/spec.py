"""Task specs: the TOML files in envs/ that size and randomise an episode.

A spec is validated on load; every error names the file, the key, what was expected and the
allowed keys, so a typo in a task file fails loudly instead of silently using a default.

``kind`` names a registered ``TaskKind`` (``pick_place``, ``lift``, ``stack``, ``tidy``, or
one registered from Python: ``so101_sim.tasks.kind``), which owns the goal and its success
rule; the other sections size and place the objects. The optional
``[randomize]`` section (``so101_sim.tasks.randomization``) turns on domain randomization.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tomllib
from dataclasses import MISSING, dataclass, fields
from pathlib import Path
from typing import Any

from so101_sim.tasks.kind import get_kind, registered_kinds
from so101_sim.tasks.randomization import Randomization, parse_randomize
from so101_sim.tasks.workspace import check_ranges
from so101_sim.utils.paths import envs_dir
from so101_sim.utils.text import did_you_mean

Range = tuple[float, float]
ALL_CAMERAS = ("front", "side", "wrist")
DEFAULT_CAMERAS = ("front", "side")
DEFAULT_TASK = "pick_place"  # the task file every command and API uses when given none


class TaskSpecError(ValueError):
    """A task spec file is missing, malformed or has an invalid value."""


@dataclass(frozen=True)
class TaskSpec:
    """Everything that defines one task variant (see envs/pick_place.toml for the meaning)."""

    name: str
    description: str
    fps: int
    physics_substeps: int
    max_steps: int
    terminate_on_success: bool
    rest_pose: tuple[float, ...]
    rest_noise: float
    cube_size: float
    cube_mass: float
    cube_x: Range
    cube_y: Range
    cube_yaw: Range
    target_x: Range
    target_y: Range
    target_radius: float
    settle_steps: int
    max_speed: float
    release_clearance: float
    shadows: bool
    msaa: bool
    mesh_grid: float
    source: str = ""
    # The suite's additions. Defaults describe pick_place, and to_dict() leaves them out
    # when at their default, so a pick_place spec hashes as it did before the suite existed.
    kind: str = "pick_place"
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    n_cubes: int = 1
    reach: Range | None = None
    min_separation: float = 0.0
    lift_height: float = 0.05
    hold_steps: int = 30
    base_size: float = 0.03
    wall_height: float = 0.025
    wall_thickness: float = 0.006
    randomize: Randomization | None = None

    @property
    def control_dt(self) -> float:
        return 1.0 / self.fps

    @property
    def physics_dt(self) -> float:
        return 1.0 / (self.fps * self.physics_substeps)

    def to_dict(self) -> dict[str, Any]:
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in _SUITE_FIELDS and value == f.default:
                continue  # see the comment on `kind`
            out[f.name] = value.to_dict() if isinstance(value, Randomization) else value
        return out

    def sha256(self) -> str:
        """Digest of the task's settings, not of where they were read from: two runs with
        equal digests ran the same task."""
        settings = {k: v for k, v in self.to_dict().items() if k != "source"}
        return hashlib.sha256(json.dumps(settings, sort_keys=True, default=list).encode()
                              ).hexdigest()


_SUITE_FIELDS = frozenset({"kind", "cameras", "n_cubes", "reach", "min_separation",
                           "lift_height", "hold_steps", "base_size", "wall_height",
                           "wall_thickness", "randomize"})


# (section, key) -> (field name, value rule). Rules: int+, float+, float>=0, bool, str, range,
# pose6, cameras.
_SCHEMA: dict[str, dict[str, tuple[str, str]]] = {
    "": {"name": ("name", "str"), "description": ("description", "str"),
         "kind": ("kind", "str")},
    "episode": {
        "fps": ("fps", "int+"),
        "physics_substeps": ("physics_substeps", "int+"),
        "max_steps": ("max_steps", "int+"),
        "terminate_on_success": ("terminate_on_success", "bool"),
    },
    "robot": {"rest_pose": ("rest_pose", "pose6"), "rest_noise": ("rest_noise", "float>=0")},
    "cube": {
        "size": ("cube_size", "float+"),
        "mass": ("cube_mass", "float+"),
        "x": ("cube_x", "range"),
        "y": ("cube_y", "range"),
        "yaw": ("cube_yaw", "range"),
    },
    "target": {
        "x": ("target_x", "range"),
        "y": ("target_y", "range"),
        "radius": ("target_radius", "float+"),
    },
    "success": {
        "settle_steps": ("settle_steps", "int+"),
        "max_speed": ("max_speed", "float+"),
        "release_clearance": ("release_clearance", "float>=0"),
        "lift_height": ("lift_height", "float+"),
        "hold_steps": ("hold_steps", "int+"),
    },
    "layout": {"reach": ("reach", "range"), "min_separation": ("min_separation", "float>=0")},
    "stack": {"base_size": ("base_size", "float+")},
    "box": {"cubes": ("n_cubes", "int+"), "wall_height": ("wall_height", "float+"),
            "wall_thickness": ("wall_thickness", "float+")},
    "render": {
        "shadows": ("shadows", "bool"),
        "msaa": ("msaa", "bool"),
        "mesh_grid": ("mesh_grid", "float>=0"),
        "cameras": ("cameras", "cameras"),
    },
}
_DEFAULTS = {"rest_noise": 0.0, "terminate_on_success": True, "shadows": False, "msaa": False,
             "mesh_grid": 0.0, "description": "Pick up the red cube and place it on the target."}

_EXPECTED = {
    "int+": "a positive integer",
    "float+": "a positive number",
    "float>=0": "a number >= 0",
    "bool": "true or false",
    "str": "a string",
    "range": "[low, high] with low <= high",
    "pose6": "a list of 6 numbers (LeRobot units)",
    "cameras": f"a non-empty list of distinct camera names from {list(ALL_CAMERAS)}",
}


def _limits(spec: TaskSpec) -> list[tuple[str, int, int, str]]:
    """Upper bounds that keep one step() and one episode finite in time: a typo such as
    physics_substeps = 100000000 would otherwise hang the first step for hours."""
    return [("episode.fps", spec.fps, 1000, "control rate in Hz"),
            ("episode.physics_substeps", spec.physics_substeps, 1000,
             "physics steps per control step; 8 gives 240 Hz physics at 30 fps"),
            ("episode.max_steps", spec.max_steps, 1_000_000,
             "control steps per episode; 300 is 10 s at 30 fps"),
            ("success.settle_steps", spec.settle_steps, spec.max_steps,
             "it must fit in an episode")]


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _convert(value: Any, rule: str) -> Any | None:
    """Return the converted value, or None when it does not match `rule`."""
    if rule == "int+":
        is_int = isinstance(value, int) and not isinstance(value, bool)
        return value if is_int and value > 0 else None
    if rule == "float+":
        return float(value) if _is_num(value) and value > 0 else None
    if rule == "float>=0":
        return float(value) if _is_num(value) and value >= 0 else None
    if rule == "bool":
        return value if isinstance(value, bool) else None
    if rule == "str":
        return value if isinstance(value, str) else None
    if rule == "range":
        ok = isinstance(value, list) and len(value) == 2 and all(map(_is_num, value))
        return (float(value[0]), float(value[1])) if ok and value[0] <= value[1] else None
    if rule == "pose6":
        ok = isinstance(value, list) and len(value) == 6 and all(map(_is_num, value))
        return tuple(float(v) for v in value) if ok else None
    if rule == "cameras":
        ok = (isinstance(value, list) and value and len(set(value)) == len(value)
              and all(v in ALL_CAMERAS for v in value))
        return tuple(value) if ok else None
    raise AssertionError(rule)


def available_tasks() -> list[str]:
    return sorted(p.stem for p in envs_dir().glob("*.toml"))


def resolve_task_path(task: str | Path) -> Path:
    """A task name in envs/ or a path to a TOML file. A bare name of the suite wins over a file
    or folder of that name in the working directory (``record --task lift --out lift``)."""
    path, text = Path(task), str(task)
    own = envs_dir() / f"{text}.toml"
    if not text.endswith(".toml") and not {"/", os.sep} & set(text) and own.is_file():
        return own
    if path.suffix == ".toml" or path.exists():
        if path.is_dir():
            raise TaskSpecError(f"task {str(path)!r} is a folder, not a task file; pass a name "
                                f"from {available_tasks()} or the path of a .toml file")
        if not path.is_file():
            raise TaskSpecError(f"task file {str(path)!r} does not exist; pass a name from "
                                f"{available_tasks()} or an existing .toml path")
        return path
    names = available_tasks()
    raise TaskSpecError(f"unknown task {text!r}{did_you_mean(text, names)}; expected one of "
                        f"{names} or a path to a task .toml file")


def task_ref(spec: TaskSpec) -> str:
    """How to name `spec` again later (sidecars, --resume): its name if it is the suite's own
    file in envs/, else the absolute path of the file it was loaded from."""
    source = Path(spec.source) if spec.source else None
    if source is None or not source.is_file():
        return spec.name
    own = envs_dir() / f"{source.stem}.toml"
    if own.is_file() and own.resolve() == source.resolve():
        return source.stem
    return str(source.resolve())


def load_task(task: str | Path | TaskSpec = DEFAULT_TASK) -> TaskSpec:
    """Load and validate a task spec by name or path."""
    if isinstance(task, TaskSpec):
        return task
    path = resolve_task_path(task)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise TaskSpecError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); save the "
                            "task file as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise TaskSpecError(f"{path}: not valid TOML ({exc})") from exc
    return parse_task(raw, source=str(path))


def loads_here(task: str | Path) -> bool:
    """Whether `task` loads on this machine (a .toml path recorded elsewhere may not): what a
    default taken from a checkpoint or a dataset checks before it is used."""
    try:
        load_task(task)
    except (OSError, ValueError):
        return False
    return True


def parse_task(raw: dict[str, Any], source: str = "<dict>") -> TaskSpec:
    values: dict[str, Any] = dict(_DEFAULTS)
    kind = raw.get("kind", "pick_place")
    if not isinstance(kind, str) or kind not in registered_kinds():
        raise TaskSpecError(f"{source}: kind = {kind!r} is invalid; expected one of "
                            f"{list(registered_kinds())}, or a kind registered from Python "
                            "with @so101_sim.tasks.register_kind")
    values.update(get_kind(kind).spec_defaults)  # sections the kind does not use
    for section, content in raw.items():
        if section == "randomize" and isinstance(content, dict):
            try:
                values["randomize"] = parse_randomize(content, source)
            except ValueError as exc:
                raise TaskSpecError(str(exc)) from None
            continue
        if isinstance(content, dict):
            if section not in _SCHEMA or section == "":
                allowed = sorted([*(s for s in _SCHEMA if s), "randomize"])
                raise TaskSpecError(f"{source}: unknown section [{section}]"
                                    f"{did_you_mean(section, allowed)}; allowed sections: "
                                    f"{allowed}")
            items = content.items()
            schema = _SCHEMA[section]
        else:
            items = [(section, content)]
            section, schema = "", _SCHEMA[""]
        for key, value in items:
            qualified = f"{section}.{key}" if section else key
            if key not in schema:
                where = f"[{section}]" if section else "the top level"
                raise TaskSpecError(f"{source}: unknown key {qualified!r}"
                                    f"{did_you_mean(key, schema)}; allowed keys in {where}: "
                                    f"{sorted(schema)}")
            field_name, rule = schema[key]
            converted = _convert(value, rule)
            if converted is None:
                raise TaskSpecError(f"{source}: {qualified} = {value!r} is invalid; expected "
                                    f"{_EXPECTED[rule]}")
            values[field_name] = converted
    required = [f.name for f in fields(TaskSpec)
                if f.name not in values and f.default is MISSING]
    if required:
        keys = [f"{s}.{k}" if s else k for s, sch in _SCHEMA.items() for k, (fn, _) in sch.items()
                if fn in required]
        raise TaskSpecError(f"{source}: missing required keys {keys}")
    spec = TaskSpec(**values, source=source)
    for key, value, limit, why in _limits(spec):
        if value > limit:
            raise TaskSpecError(f"{source}: {key} = {value} is too large; expected at most "
                                f"{limit} ({why})")
    if spec.cube_size < 0.01 or spec.cube_size > 0.05:
        raise TaskSpecError(f"{source}: cube.size = {spec.cube_size} is invalid; expected "
                            "0.01 .. 0.05 m (the gripper opens to about 6 cm)")
    _check_kind(spec, source)
    problem = check_ranges(spec, has_target="target" in raw)  # on the table, in reach
    if problem:
        raise TaskSpecError(f"{source}: {problem}")
    return spec


def _check_kind(spec: TaskSpec, source: str) -> None:
    """Rules that depend on the task's kind, and the kind's own (``TaskKind.check``)."""
    kind = get_kind(spec.kind)
    if spec.n_cubes > kind.max_cubes:
        many = [k for k in registered_kinds() if get_kind(k).max_cubes > 1]
        raise TaskSpecError(f"{source}: box.cubes = {spec.n_cubes} is invalid for kind "
                            f"{spec.kind!r}; expected 1..{kind.max_cubes} (kinds with several "
                            f"cubes: {many})")
    problem = kind.check(spec, source)
    if problem:
        raise TaskSpecError(f"{source}: {problem}")
    if not 0.015 <= spec.base_size <= 0.05:
        raise TaskSpecError(f"{source}: stack.base_size = {spec.base_size} is invalid; "
                            "expected 0.015 .. 0.05 m")
    if spec.reach is not None and spec.reach[0] <= 0:
        raise TaskSpecError(f"{source}: layout.reach = {list(spec.reach)} is invalid; expected "
                            "[low, high] distances from the base's pan axis with low > 0, "
                            "e.g. [0.12, 0.26]")

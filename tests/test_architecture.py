"""The package reads as the pipeline: imports flow down it, never up or around in a circle.

Layers, bottom first: utils -> workers -> tasks -> sim -> expert -> dataset -> record -> train
-> harness -> explain -> the faces on top (cli, lerobot_plugin, hub_env, testing, and the
deprecated re-exports). A module may import its own layer or lower ones. Imports under
``if TYPE_CHECKING:`` are annotations only and do not count.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import so101_sim

PKG = Path(so101_sim.__file__).parent
LAYERS = ["utils", "workers", "tasks", "sim", "expert", "dataset", "record", "train", "harness",
          "explain", "cli"]
TOP = len(LAYERS)  # modules directly in so101_sim/


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _runtime_imports(path: Path, module: str) -> list[tuple[str, list[str]]]:
    """(module imported, names taken from it) for every import that runs."""
    tree = ast.parse(path.read_text())
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names if a.name.startswith("so101_sim")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.startswith("so101_sim"):
                found.append((name, [a.name for a in node.names]))
    return found


def _graph() -> dict[str, set[str]]:
    mods = _modules()

    def resolve(name: str) -> str:
        while name not in mods:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        for name, names in _runtime_imports(path, mod):
            targets = [f"{name}.{n}" for n in names if f"{name}.{n}" in mods] or [name]
            graph[mod].update(resolve(t) for t in targets if resolve(t) != mod)
    return graph


def _layer(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1 or parts[1] not in LAYERS:
        return TOP
    return LAYERS.index(parts[1])


def test_no_import_circles():
    graph = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert circles == []


def test_data_flows_down_the_pipeline():
    upward = [f"{m} -> {t}" for m, targets in _graph().items() for t in targets
              if _layer(t) > _layer(m)]
    assert upward == []


def test_no_file_imports_another_files_private_names():
    private = [f"{m}: {name}.{n}" for m, path in _modules().items()
               for name, names in _runtime_imports(path, m) for n in names
               if n.startswith("_") and not n.startswith("__")]
    assert private == []


def test_a_short_top_level_and_short_modules():
    top = sorted(p.name for p in PKG.glob("*.py"))
    assert len(top) <= 12, top
    plugin = PKG.parent / "plugins" / "lerobot_robot_so101_sim"  # its package and script too
    long = {str(p.relative_to(PKG.parent)): n for p in [*PKG.rglob("*.py"), *plugin.rglob("*.py")]
            if (n := len(p.read_text().splitlines())) > 400}
    assert long == {}


def test_public_functions_have_type_hints():
    # every argument and the return of each public function and method, nested ones included
    plugin = PKG.parent / "plugins" / "lerobot_robot_so101_sim" / "lerobot_robot_so101_sim"
    bare = []
    for path in [*PKG.rglob("*.py"), *plugin.rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) \
                    or node.name.startswith("_"):
                continue
            args = [a for a in [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]
                    if a.arg not in ("self", "cls")]
            if node.returns is None or any(a.annotation is None for a in args):
                bare.append(f"{path.relative_to(PKG.parent)}:{node.lineno} {node.name}")
    assert bare == []


def test_every_package_face_declares_all():
    faces = [p for p in PKG.rglob("__init__.py")]
    missing = [str(p.relative_to(PKG)) for p in faces if "__all__" not in p.read_text()]
    assert missing == []


def test_no_branches_on_the_task_kind_outside_the_kinds():
    # A kind's behaviour lives in its TaskKind (so101_sim/tasks/<kind>.py), asked by method.
    pattern = ("task.kind ==", "task.kind !=", "task.kind in", "spec.kind ==", "spec.kind in",
               'kind == "pick_place"', 'kind == "lift"', 'kind == "stack"', 'kind == "tidy"')
    hits = [f"{p.relative_to(PKG)}: {line.strip()}" for p in PKG.rglob("*.py")
            for line in p.read_text().splitlines() if any(s in line for s in pattern)]
    assert hits == []


def test_import_so101_sim_and_its_faces_stay_light():
    code = ("import sys, so101_sim, so101_sim.tasks, so101_sim.sim, so101_sim.expert, "
            "so101_sim.dataset, so101_sim.record, so101_sim.train, so101_sim.harness, "
            "so101_sim.explain, so101_sim.workers, so101_sim.cli; "
            "print(sorted(m for m in ('torch', 'ray', 'lerobot') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_the_cli_spells_out_the_packages_defaults():
    # The CLI writes them as literals, so that it does not import the tasks and dataset
    # packages to build its parser; they must still be the package's own.
    from so101_sim.cli import build_parser
    from so101_sim.cli.commands import EVAL_DEFAULTS
    from so101_sim.dataset import EVAL_SEED_START
    from so101_sim.tasks import DEFAULT_TASK

    assert (EVAL_DEFAULTS["task"], EVAL_DEFAULTS["seed_start"]) == (DEFAULT_TASK, EVAL_SEED_START)
    parser = build_parser()
    assert parser.parse_args(["demo"]).task == DEFAULT_TASK
    assert parser.parse_args(["curve", "run"]).seed_start == EVAL_SEED_START


@pytest.mark.parametrize(("old", "new", "name"), [
    ("so101_sim.env", "so101_sim.sim", "SO101Env"),
    ("so101_sim.recording", "so101_sim.record", "record"),
    ("so101_sim.recording", "so101_sim.dataset", "stored_seeds"),
    ("so101_sim.stats", "so101_sim.harness.stats", "wilson_interval"),
])
def test_old_module_paths_still_work_and_warn(old, new, name):
    import importlib

    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    assert any(issubclass(w.category, DeprecationWarning) and new in str(w.message)
               for w in caught)
    assert getattr(module, name) is getattr(importlib.import_module(new), name)

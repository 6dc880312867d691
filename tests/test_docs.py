"""What the docs tell users to run works as written: `so101-sim`, lerobot's and the benchmark
scripts' commands parse, the names they give in the package exist, and the code examples run and
do what they say."""

from __future__ import annotations

import ast
import importlib
import inspect
import json
import logging
import re
import shlex
import subprocess
import sys
import tempfile
import warnings
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"(?:\S*/)?so101-sim\s+(.*)")  # so101-sim ..., .venv/bin/so101-sim ...


def shown_lines(path: Path) -> list[str]:
    """The shell lines of `path`, comments cut: in ```bash blocks, or indented 4 spaces; of a
    script, those of its docstring (its usage)."""
    if path.suffix == ".py":
        return shell_lines(ast.get_docstring(ast.parse(path.read_text())) or "")
    return shell_lines(path.read_text())


def shell_lines(text: str) -> list[str]:
    """The shell lines of a doc's or a docstring's `text` (see `shown_lines`)."""
    found, fenced, lang = [], False, ""
    text = text.replace("\\\n", " ")  # a continued command is one line
    for line in text.splitlines():
        if line.startswith("```"):
            fenced, lang = not fenced, line[3:].strip()
            continue
        if (fenced and lang in ("bash", "")) or (not fenced and line.startswith("    ")):
            found.append(line.strip().split(" #")[0])
    return found


def shown_commands(path: Path) -> list[str]:
    """The arguments of each `so101-sim` command line `path` shows."""
    return [m.group(1) for line in shown_lines(path) if (m := COMMAND.match(line))]


# what the docs put where a value goes: a metavar (`--seed-start SEED`) or a loop's `$s`
PLACEHOLDER = re.compile(r"[A-Z][A-Z_]*|\$\w+")


def refuses_only_a_placeholder(said: str, args: list[str]) -> bool:
    """Whether the error `said` names one of the placeholders in `args`: the flag exists, and
    only the placeholder standing for its value is not one."""
    return any(f"'{arg}'" in said for arg in args if PLACEHOLDER.fullmatch(arg))


def test_documented_commands_parse(capsys) -> None:
    from so101_sim.cli.parser import build_parser

    shown = [(doc.relative_to(ROOT), command)
             for doc in doc_files(".md") + script_files() for command in shown_commands(doc)]
    per_doc = Counter(str(doc) for doc, _ in shown)  # the docs show a command-line workflow
    assert min(per_doc["README.md"], per_doc["benchmarks/README.md"]) >= 10, per_doc
    parser = build_parser()
    refused = []
    for doc, command in shown:
        args = shlex.split(command)
        try:
            parser.parse_args(args)
        except SystemExit:
            said = capsys.readouterr().err.strip().splitlines()[-1]
            if not refuses_only_a_placeholder(said, args):
                refused.append(f"{doc}: so101-sim {command}\n  -> {said}")
    assert refused == [], "\n".join(refused)


DOTTED = re.compile(r"(?<![\w.])so101_sim(?:\.[A-Za-z_]\w*)+")
DOC_FILES = ("*.md", "docs/*.md", "benchmarks/**/*.md", "plugins/**/*.md", "envs/*.toml",
             "policy/**/*.md", "policy/**/*.json", "policy/presets/*.toml")


def resolves(name: str) -> bool:
    """Whether `name` (so101_sim.module.attribute...) imports: its longest module, then
    attributes on it."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            with warnings.catch_warnings():  # the old module paths warn, and still count
                warnings.simplefilter("ignore", DeprecationWarning)
                obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def doc_files(suffix: str = "") -> list[Path]:
    """The files of DOC_FILES whose names end with `suffix`."""
    return sorted({p for pattern in DOC_FILES if pattern.endswith(suffix)
                   for p in ROOT.glob(pattern)})


def test_the_package_names_the_docs_give_exist() -> None:
    # the docs, model cards and preset comments; a module moved in a restructure left its old
    # name in a card and two presets before
    docs = doc_files()
    assert ROOT / "README.md" in docs and ROOT / "policy/presets/cpu.toml" in docs
    where: dict[str, list[str]] = {}  # each name is resolved once, wherever it is given
    for path in docs:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for name in DOTTED.findall(line):
                where.setdefault(name, []).append(f"{path.relative_to(ROOT)}:{n}")
    missing = [f"{place}: {name}" for name, places in where.items() if not resolves(name)
               for place in places]
    assert missing == []


# each lerobot command the docs show: the module its console script (or `python -m`) runs, and
# the function there whose config the command line fills
LEROBOT_COMMANDS = {
    "lerobot-record": ("lerobot.scripts.lerobot_record", "record"),
    "lerobot-replay": ("lerobot.scripts.lerobot_replay", "replay"),
    "lerobot-teleoperate": ("lerobot.scripts.lerobot_teleoperate", "teleoperate"),
    "lerobot-rollout": ("lerobot.scripts.lerobot_rollout", "rollout"),
    "lerobot-eval": ("lerobot.scripts.lerobot_eval", "eval_main"),
    "lerobot-train": ("lerobot.scripts.lerobot_train", "train"),
    "python -m lerobot.async_inference.policy_server": (
        "lerobot.async_inference.policy_server", "serve"),
    "python -m lerobot.async_inference.robot_client": (
        "lerobot.async_inference.robot_client", "async_client"),
}
LEROBOT_COMMAND = re.compile(r"(lerobot-[a-z-]+|python -m lerobot\.[\w.]+)\s+(.*)")


def parse_as_lerobot_does(command: str, args: list[str], monkeypatch) -> object:
    """The config `command` builds from `args` before it starts any work: lerobot's own
    parser (its `.path` and plugin handling for the `lerobot-*` scripts, draccus for the
    async modules), then `validate()`, which lerobot-train runs first."""
    import draccus
    from lerobot.configs import parser

    module, name = LEROBOT_COMMANDS[command]
    inner = getattr(importlib.import_module(module), name).__wrapped__
    spec = inspect.getfullargspec(inner)
    config_class = spec.annotations[spec.args[0]]
    monkeypatch.setattr(sys, "argv", [command, *args])  # the `.path` fields read argv
    if command.startswith("python -m"):
        cfg = draccus.parse(config_class=config_class, args=args)
    else:
        def capture(cfg):
            return cfg
        capture.__annotations__ = {"cfg": config_class}
        cfg = parser.wrap()(capture)()
    if hasattr(cfg, "validate"):
        cfg.validate()
    return cfg


def import_from(modules: list[str], where: Path, monkeypatch) -> None:
    """Import `modules` with `where` as the cwd. lerobot's async modules, once imported, log to
    logs/<name>_<time>.log under the cwd in place of the root logger's handlers: the file is
    closed and the handlers put back."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    with monkeypatch.context() as m:
        m.chdir(where)
        for module in modules:
            importlib.import_module(module)
    for handler in root.handlers:
        if handler not in handlers:
            handler.close()
    root.handlers[:] = handlers
    root.setLevel(level)


def test_documented_lerobot_commands_parse(monkeypatch, capsys, tmp_path) -> None:
    # lerobot's CLIs fail on an unknown or misspelt flag, or a bad value of the sim's robot and
    # env configs, before anything runs; tests/test_lerobot_robot.py runs them with test sizes
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()  # what each lerobot entry point does first
    import_from([module for module, _ in LEROBOT_COMMANDS.values()], tmp_path, monkeypatch)
    monkeypatch.chdir(ROOT)  # the docs' relative paths (policy/pick_place_diffusion)
    # lerobot's PreTrainedConfig.from_pretrained (--policy.path) leaves a tmp*.json behind
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    shown = []
    for doc in doc_files(".md"):  # the READMEs, docs/ and the model cards
        for line in shown_lines(doc):
            if m := LEROBOT_COMMAND.match(line):
                shown.append((doc.relative_to(ROOT), m.group(1), m.group(2)))
    assert {command for _, command, _ in shown} == set(LEROBOT_COMMANDS)
    refused = []
    for doc, command, args in shown:
        try:
            parse_as_lerobot_does(command, shlex.split(args), monkeypatch)
        except (SystemExit, Exception) as e:  # argparse exits; a config's checks raise
            said = capsys.readouterr().err.strip().splitlines()
            refused.append(f"{doc}: {command} {args}\n  -> {said[-1] if said else repr(e)}")
    assert refused == [], "\n".join(refused)


# a script the docs run: `benchmarks/x.py ARGS`, `python plugins/p/x.py ARGS`, ...
SCRIPT_COMMAND = re.compile(
    r"(?:\S*python\S*\s+)?(?:\S*/)?((?:benchmarks|plugins)/[\w/]+\.py)\b\s*(.*)")


def script_files() -> list[Path]:
    """The benchmark and plugin scripts, whose docstrings give their usage."""
    return sorted({*ROOT.glob("benchmarks/**/*.py"), *ROOT.glob("plugins/**/*.py")})


def synopsis_args(args: str) -> list[str]:
    """A usage line's arguments as a command line: `[--steps 20]` gives `--steps 20` (the
    optional flags it shows must exist too), `...` (more of the same) is left out."""
    return [token.strip("[]") for token in shlex.split(args) if token.strip("[]") != "..."]


def shown_script_lines(path: Path) -> list[str]:
    """The shell lines of a doc or a script's docstring, and a doc's inline `code` that runs a
    script with arguments (the prose cites the command behind a number that way)."""
    if path.suffix == ".py":
        return shown_lines(path)
    inline = [span for span in re.findall(r"`([^`\n]+)`", path.read_text())
              if (m := SCRIPT_COMMAND.match(span)) and m.group(2).strip()]
    return shown_lines(path) + inline


def test_documented_script_commands_parse(tmp_path) -> None:
    # the benchmark lines are how each number in the docs is reproduced, and the plugin's
    # agreement.py is how lerobot's tools are paired with ours: a flag renamed or dropped in a
    # script leaves its command in the docs failing as written
    docs = doc_files(".md") + script_files()
    shown = [(doc.relative_to(ROOT), m.group(1), m.group(2), synopsis_args(m.group(2)))
             for doc in docs for line in shown_script_lines(doc)
             if (m := SCRIPT_COMMAND.match(line))]
    scripts = {script for _, script, _, _ in shown}
    assert {"benchmarks/bench_eval.py", "benchmarks/bench_against.py",
            "plugins/lerobot_robot_so101_sim/agreement.py"} <= scripts, scripts
    lines = json.dumps([(script, argv) for _, script, _, argv in shown])
    run = subprocess.run([sys.executable, str(ROOT / "tests/script_parse.py")], input=lines,
                         cwd=tmp_path, capture_output=True, text=True, timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    said = json.loads(run.stdout)
    refused = [f"{doc}: {script} {args}\n  -> {why}"
               for (doc, script, args, argv), why in zip(shown, said, strict=True)
               if why and not refuses_only_a_placeholder(why, argv)]
    assert refused == [], "\n".join(refused)


def python_blocks(path: Path, heading: str) -> list[str]:
    """The ```python blocks of the section `heading` of `path`, in order."""
    section = path.read_text().split(f"\n{heading}\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def run_python(script: str, cwd: Path) -> str:
    """The last line `script` prints, run by this Python in a process of its own from `cwd`."""
    run = subprocess.run([sys.executable, "-c", script], cwd=cwd, capture_output=True,
                         text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout.splitlines()[-1]


def test_the_task_kind_example_in_the_docs_runs(tmp_path) -> None:
    # a reader copies the kind into a module of theirs and runs the two lines that follow it;
    # in a process of its own, as it registers "shelf" over tests/shelf_kind.py's
    kind, use = python_blocks(ROOT / "docs/architecture.md", "## Adding a task kind")
    (tmp_path / "my_kinds.py").write_text(kind)
    assert '"path/to/shelf.toml"' in use
    use = use.replace('"path/to/shelf.toml"', repr(str(ROOT / "tests/shelf.toml")))
    script = "\n".join([
        "import my_kinds", use,
        "obs, _ = env.reset(seed=0)",
        "expert.reset(0)",
        "done = False",
        "while not done:",
        "    obs, reward, terminated, truncated, info = env.step(expert.select_action(obs))",
        "    done = terminated or truncated",
        "print(env.task.kind, info['is_success'], info['failure_mode'], env.cube_pos(0)[2])"])
    kind_name, success, failure, height = run_python(script, tmp_path).split()
    assert (kind_name, success, failure) == ("shelf", "True", "None")
    assert float(height) > 0.02  # on the board, not on the table beside it


def test_the_readmes_env_example_runs_and_gives_what_it_says(tmp_path) -> None:
    # the first code a reader runs: the obs it documents in its comment, and front|side frames
    (block,) = python_blocks(ROOT / "README.md", "## Using the env")
    said = re.search(r"# obs = (\{.*\})", block).group(1)
    assert said == ('{"pixels": {"front": uint8[480,640,3], "side": uint8[480,640,3]}, '
                    '"agent_pos": float32[6]}')
    script = block + "\n".join([
        "", "def shape(a):", "    return f'{a.dtype}[{\",\".join(map(str, a.shape))}]'",
        "half = frame.shape[1] // 2  # front, then side: two different pictures",
        "print({k: shape(v) for k, v in obs['pixels'].items()}, shape(obs['agent_pos']),",
        "      shape(frame), bool(abs(frame[:, :half].astype(int) - frame[:, half:]).mean() > 1))"])
    assert run_python(script, tmp_path) == ("{'front': 'uint8[480,640,3]', 'side': "
                                           "'uint8[480,640,3]'} float32[6] uint8[480,1280,3] True")

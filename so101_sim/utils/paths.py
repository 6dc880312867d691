"""Where the package's data folders (assets/, envs/, policy/) live.

In a source checkout they sit next to the package; in a wheel they are shipped inside it
(see `[tool.hatch.build.targets.wheel.force-include]` in pyproject.toml).
"""

from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent.parent  # so101_sim/


def data_dir(name: str) -> Path:
    """Return the folder `name` ("assets", "envs" or "policy"), installed or from the repo."""
    for candidate in (PACKAGE_DIR / name, PACKAGE_DIR.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f"so101_sim data folder {name!r} not found next to {PACKAGE_DIR} or inside it; "
        "the installation is incomplete: reinstall so101-sim (pip install --force-reinstall)."
    )


def assets_dir() -> Path:
    return data_dir("assets")


def envs_dir() -> Path:
    return data_dir("envs")


def policy_dir() -> Path:
    return data_dir("policy")


SHIPPED_POLICY = "pick_place_diffusion"


def shipped_policy_dir() -> Path:
    """The trained checkpoint shipped in the repo (policy/pick_place_diffusion)."""
    return policy_dir() / SHIPPED_POLICY


def foreign_folder(path: Path) -> str | None:
    """What `path` already is if it belongs to another tool's output, which an ``--out`` must
    not write among: a policy checkpoint or a LeRobotDataset (None: neither)."""
    if (path / "model.safetensors").is_file():
        return "holds a policy checkpoint (model.safetensors)"
    if (path / "meta" / "info.json").is_file():
        return "is a LeRobotDataset (meta/info.json)"
    return None


def hub_id_hint(path: Path, flag: str, dataset: bool = False) -> str:
    """For a `USER/REPO` given where a folder is expected (lerobot's --policy.path and
    --dataset.repo_id habit) and no such folder here: how to fetch it once, since so101-sim
    reads local folders only and nothing downloads at run time. "" for anything else."""
    text = str(path)
    if (text.count("/") != 1 or path.is_absolute() or path.exists()
            or path.parent.exists()):  # a local folder's missing child: not a repo id
        return ""
    kind = " --repo-type dataset" if dataset else ""
    return (f"; {text!r} looks like a Hugging Face Hub repo id, and so101-sim reads local "
            f"folders only: fetch it once with `hf download {text}{kind} --local-dir "
            f"{path.name}` and pass {flag} {path.name}")

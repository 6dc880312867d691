"""Checkpoints from other people are data: refuse processor files that would import code.

lerobot rebuilds a policy's pre/post-processors from `policy_preprocessor.json` /
`policy_postprocessor.json`. A step given by ``registry_name`` is looked up among the steps
lerobot registers; a step given by ``"class": "pkg.mod.Name"`` is imported and called, so a
downloaded checkpoint could name `os.system` and run a command. `check_processor_files` reads
those files as JSON and accepts only registered step names (and state files that are plain
names inside the checkpoint) before anything is instantiated.
"""

from __future__ import annotations

import contextlib
import importlib
import json
from pathlib import Path

PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")


class UntrustedCheckpointError(ValueError):
    """A checkpoint file asks for something that would run code or read outside the folder."""


def registered_steps(policy_type: str | None = None) -> set[str]:
    """Registry names of lerobot's processor steps (plus those of `policy_type`'s module)."""
    import lerobot.processor  # noqa: F401  (registers the generic steps)
    from lerobot.processor import ProcessorStepRegistry

    if policy_type and policy_type.isidentifier():
        # A policy's own steps register when its processor module is imported.
        with contextlib.suppress(ImportError):
            importlib.import_module(f"lerobot.policies.{policy_type}.processor_{policy_type}")
    return set(ProcessorStepRegistry.list())


def check_processor_files(checkpoint: str | Path, policy_type: str | None = None) -> None:
    """Raise `UntrustedCheckpointError` unless every processor step in `checkpoint` is a step
    lerobot registers by name; a missing processor file is left to the loader to report."""
    root = Path(checkpoint)
    allowed: set[str] | None = None
    for name in PROCESSOR_FILES:
        path = root / name
        if not path.is_file():
            continue
        try:
            spec = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise UntrustedCheckpointError(f"{path} is not valid UTF-8 JSON ({e}); re-export "
                                           "the checkpoint or fetch it again") from None
        steps = spec.get("steps") if isinstance(spec, dict) else None
        if not isinstance(steps, list):
            raise UntrustedCheckpointError(f"{path} has no 'steps' list; expected a lerobot "
                                           "processor file")
        for i, step in enumerate(steps):
            if not isinstance(step, dict):
                raise UntrustedCheckpointError(f"{path}: step {i} is not an object")
            if "class" in step:
                raise UntrustedCheckpointError(
                    f"{path}: step {i} names the Python class {step['class']!r}; loading it "
                    "would import and run that code, so this checkpoint is refused. Only steps "
                    "lerobot registers by 'registry_name' are loaded; if you trust the author, "
                    "register the step in your own code and load the checkpoint there")
            reg = step.get("registry_name")
            if allowed is None:
                allowed = registered_steps(policy_type)
            if reg not in allowed:
                raise UntrustedCheckpointError(
                    f"{path}: step {i} has registry_name {reg!r}, which is not a processor "
                    f"step lerobot registers (known: {', '.join(sorted(allowed))}); refused")
            state = step.get("state_file")
            if state is not None and (not isinstance(state, str) or Path(state).name != state
                                      or state.startswith(".")):
                raise UntrustedCheckpointError(
                    f"{path}: step {i} ({reg}) points its state_file at {state!r}; expected a "
                    "plain file name inside the checkpoint folder")

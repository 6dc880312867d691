"""What a run's numbers depend on besides the policy: software versions and the CPU.

A policy's actions differ bitwise across torch releases and CPU instruction sets (oneDNN picks
other kernels), and physics across MuJoCo releases; closed-loop rollouts then part ways on some
seeds. ``eval`` records both in ``eval_info.json`` so that ``compare`` and ``eval --against``
can say when two paired runs did not share them.
"""

from __future__ import annotations

import contextlib
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

#: Distributions whose versions change what the suite computes (physics, policy, env API).
DISTRIBUTIONS = ("so101-sim", "mujoco", "lerobot", "torch", "gymnasium")
#: The keys of an eval's config that say what it ran on: ``run_setup``'s, and the setups a
#: resumed run's earlier episodes ran with (``harness.results.RunDir``).
SETUP_KEYS = ("software", "cpu", "cpu_isa", "earlier_setups")


def installed(dist: str) -> str | None:
    """The installed version of distribution `dist` (None: not installed); imports nothing."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def software_versions() -> dict[str, str | None]:
    """{distribution: version} for DISTRIBUTIONS, and Python's."""
    return {**{d: installed(d) for d in DISTRIBUTIONS}, "python": platform.python_version()}


def cpu_description() -> str:
    """The CPU's model name, e.g. "AMD EPYC"."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def torch_cpu_isa() -> str | None:
    """The instruction set torch's CPU kernels use (e.g. "AVX2"), if torch is loaded."""
    torch = sys.modules.get("torch")
    if torch is None:
        return None
    with contextlib.suppress(AttributeError, RuntimeError):  # an older torch: no such query
        return str(torch.backends.cpu.get_cpu_capability())
    return None


def run_setup() -> dict[str, Any]:
    """What ``eval`` records beside its results: ``software``, ``cpu`` and, for a policy
    that runs on torch, ``cpu_isa``."""
    isa = torch_cpu_isa()
    return {"software": software_versions(), "cpu": cpu_description(),
            **({"cpu_isa": isa} if isa else {})}


def setup_differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """How two runs' recorded setups differ, e.g. ["torch 2.11.0 vs 2.10.0", "cpu ..."];
    what either run did not record is not counted as a difference. A resumed run's
    ``earlier_setups`` count too: every one of a's against every one of b's."""
    found: list[str] = []
    for x in _setups(a):
        for y in _setups(b):
            found += [d for d in _differences(x, y) if d not in found]
    return found


def _setups(config: dict[str, Any]) -> list[dict[str, Any]]:
    earlier = config.get("earlier_setups")
    return [*(s for s in earlier if isinstance(s, dict)), config] if isinstance(
        earlier, list) else [config]


def _differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    found = []
    sa, sb = a.get("software") or {}, b.get("software") or {}
    for key in sorted(set(sa) & set(sb)):
        if sa[key] != sb[key]:
            found.append(f"{key} {sa[key]} vs {sb[key]}")
    for key, label in (("cpu", "CPU"), ("cpu_isa", "torch's CPU kernels")):
        if a.get(key) and b.get(key) and a[key] != b[key]:
            found.append(f"{label} {a[key]} vs {b[key]}")
    return found

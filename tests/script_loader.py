"""Load a script (benchmarks/*.py, plugins/*/*.py; not in the package) as a module in a test."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_script(path: Path, register: bool = False) -> ModuleType:
    """The module of the script at `path`; `register` puts it in sys.modules under its stem
    (needed when its functions are pickled by module name, e.g. for worker processes)."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    if register:
        sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module

"""Probe a headless GL backend in a child process (no mujoco import here: this also runs when
importing mujoco itself failed). PyOpenGL binds its platform on first import, hence a child."""

from __future__ import annotations

import os
import subprocess
import sys

BACKENDS = ("egl", "osmesa")
_PROBE = (
    "import os, sys; os.environ['PYOPENGL_PLATFORM'] = sys.argv[1]\n"
    "mod = __import__('mujoco.' + sys.argv[1], fromlist=['GLContext'])\n"
    "ctx = mod.GLContext(8, 8); ctx.make_current(); ctx.free()\n"
)


def probe_backend(backend: str) -> str | None:
    """Try to open a GL context with `backend` in a child process; None if it works, else the
    child's last error line."""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE, backend], env=env, timeout=60,
                              capture_output=True, text=True)
    except subprocess.TimeoutExpired:
        return "timed out"
    if proc.returncode == 0:
        return None
    lines = (proc.stderr or proc.stdout).strip().splitlines()
    return lines[-1] if lines else f"exit code {proc.returncode}"

"""Import MuJoCo with a one-line error when `MUJOCO_GL` names a backend that can't be used.

MuJoCo reads `MUJOCO_GL` when it is imported: an unknown value raises a bare RuntimeError and
a known but missing one (osmesa without libosmesa) fails deep inside PyOpenGL. The env imports
`mujoco` from here, so a user gets one line naming the variable and the backends that do work
on this machine (probed in child processes, only once something has failed).
"""

from __future__ import annotations

import os


def _working_backends() -> list[str]:
    from so101_sim.sim.rendering_probe import probe_backend

    return [b for b in ("egl", "osmesa") if probe_backend(b) is None]


try:
    import mujoco
except Exception as exc:
    value = os.environ.get("MUJOCO_GL", "")
    if not value:
        raise
    works = _working_backends()
    hint = (f"backends that work here: {', '.join(works)}; set MUJOCO_GL={works[0]} or unset it "
            "(so101_sim then picks one)" if works else
            "no headless backend works here: install Mesa's EGL (apt-get install libegl1 "
            "libgl1-mesa-dri) or OSMesa (apt-get install libosmesa6)")
    raise RuntimeError(f"MUJOCO_GL={value!r} cannot be used ({type(exc).__name__}: "
                       f"{(str(exc).splitlines() or [''])[-1]}); {hint}") from None

__all__ = ["mujoco"]

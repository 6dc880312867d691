"""Headless multi-camera rendering with MuJoCo's own OpenGL context and renderer.

All cameras are drawn side by side into one offscreen framebuffer and read back with a single
`mjr_readPixels`, and the scene is built once per frame (only the camera changes between
viewports). That is the cheapest path on a CPU rasteriser (Mesa llvmpipe).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
import weakref
from collections.abc import Sequence

import numpy as np

from so101_sim.sim.glcheck import mujoco
from so101_sim.sim.rendering_probe import BACKENDS, probe_backend

HEADLESS_HINT = ("for headless rendering set MUJOCO_GL=egl or MUJOCO_GL=osmesa, or unset it "
                 "(so101_sim then picks one)")

# Geom group of the collision primitives in assets/so101.xml (the meshes are group 2): drawn
# only when no visual mesh is found.
COLLISION_GROUP = 3


def select_gl_backend() -> str:
    """Return the headless GL backend to use, choosing (and printing) one if MUJOCO_GL is unset.

    The choice is written to MUJOCO_GL/PYOPENGL_PLATFORM so worker processes inherit it.
    The probe runs in a child process because PyOpenGL binds its platform on first import.
    """
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    pyopengl = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    device = os.environ.get("MUJOCO_EGL_DEVICE_ID")
    if chosen in ("", "egl") and device is not None and not device.strip().isdigit():
        # else MuJoCo's int() fails with "invalid literal for int()", naming no variable
        raise RuntimeError(f"MUJOCO_EGL_DEVICE_ID={device!r} is not a device index; expected "
                           "an integer from 0 (the first EGL device), or unset it")
    if chosen:
        if chosen not in (*BACKENDS, "glfw"):
            raise RuntimeError(f"MUJOCO_GL={chosen!r} is not supported by so101_sim; expected "
                               "'egl' or 'osmesa' (headless) or 'glfw' (needs a display)")
        if (chosen == "glfw" and sys.platform.startswith("linux")
                and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))):
            # else GLFW warns twice and MuJoCo fails later with "no OpenGL platform library"
            raise RuntimeError(f"MUJOCO_GL='glfw' needs a display and DISPLAY is not set here; "
                               f"{HEADLESS_HINT}")
        if chosen in BACKENDS and pyopengl and pyopengl != chosen:
            raise RuntimeError(_platform_clash(f"MUJOCO_GL={chosen!r}", chosen, pyopengl))
        return chosen
    if pyopengl and pyopengl not in BACKENDS:
        raise RuntimeError(_platform_clash("headless rendering (MUJOCO_GL unset)", "egl or osmesa",
                                           pyopengl))
    errors = {}
    for backend in (pyopengl,) if pyopengl else BACKENDS:  # PyOpenGL's platform is fixed
        err = probe_backend(backend)
        if err is None:
            os.environ["MUJOCO_GL"] = backend
            os.environ["PYOPENGL_PLATFORM"] = backend
            print(f"so101_sim: MUJOCO_GL not set; rendering with {backend}", file=sys.stderr)
            return backend
        errors[backend] = err
    if pyopengl:
        raise RuntimeError(f"PYOPENGL_PLATFORM={pyopengl!r} (MUJOCO_GL unset) leaves only "
                           f"{pyopengl}, which failed here ({errors[pyopengl]}); unset "
                           "PYOPENGL_PLATFORM to let so101_sim try EGL and OSMesa")
    raise RuntimeError(
        "no headless OpenGL found: EGL failed ({egl}); OSMesa failed ({osmesa}). Install Mesa's "
        "EGL (Debian: apt-get install libegl1 libgl1-mesa-dri) or OSMesa (apt-get install "
        "libosmesa6), or set MUJOCO_GL to a backend that works here.".format(**errors))


def _gl_context_class(backend: str) -> type:
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        from mujoco.glfw import GLContext
    return GLContext


def _platform_clash(gl: str, wants: str, pyopengl: str) -> str:
    # MuJoCo's egl/osmesa contexts are PyOpenGL's, which binds PYOPENGL_PLATFORM on import;
    # mujoco.egl's own error for this leaves the value out ("is set to {!r}").
    return (f"{gl} needs PyOpenGL on {wants}, but PYOPENGL_PLATFORM={pyopengl!r} is set; "
            f"unset PYOPENGL_PLATFORM (so101_sim then sets it to match) or set MUJOCO_GL and "
            f"PYOPENGL_PLATFORM to the same backend, egl or osmesa")


#: Near clipping plane (metres) of cameras that look at things a few centimetres away.
NEAR_CLIP = {"wrist": 0.005}

_LIVE: weakref.WeakSet[MultiCameraRenderer] = weakref.WeakSet()
_ATEXIT_REGISTERED = False
#: The parent's pid when this process was forked from one that had opened EGL's display.
_FORKED_AFTER_EGL: int | None = None


def _after_fork_in_child() -> None:
    # EGL's driver state is copied by fork() but not its threads: Mesa's llvmpipe in the copy
    # waits forever on the first frame (gym.make_vec(..., vectorization_mode="async") after a
    # render in the parent did). Remember it, to refuse with the fix rather than hang.
    global _FORKED_AFTER_EGL
    egl = sys.modules.get("mujoco.egl")
    if egl is not None and getattr(egl, "EGL_DISPLAY", None) is not None:
        _FORKED_AFTER_EGL = os.getppid()
        for renderer in list(_LIVE):  # the parent's contexts: freeing them here could hang too
            if renderer.backend == "egl":
                renderer._gl = None


os.register_at_fork(after_in_child=_after_fork_in_child)


def _forked_after_egl_error(ppid: int) -> RuntimeError:
    return RuntimeError(
        f"MUJOCO_GL='egl' cannot render in this process: it was forked from process {ppid} "
        "after that one had rendered, and EGL does not survive a fork (Mesa's renderer hangs "
        "in the copy); start the processes with 'forkserver' or 'spawn' instead: "
        "gym.make_vec(..., vectorization_mode='async', vector_kwargs={'context': "
        "'forkserver'}), gym.vector.AsyncVectorEnv(fns, context='forkserver') or "
        "multiprocessing.get_context('forkserver'); or fork before the first render")


def _close_all() -> None:
    for renderer in list(_LIVE):
        renderer.close()


def _register_atexit() -> None:
    # Registered after mujoco.egl/osmesa's own atexit hook (which terminates the display), so
    # ours runs first (LIFO) and frees our contexts while the display is still alive.
    global _ATEXIT_REGISTERED
    if not _ATEXIT_REGISTERED:
        atexit.register(_close_all)
        _ATEXIT_REGISTERED = True


class MultiCameraRenderer:
    """Renders fixed cameras of one model side by side: (H, W * n_cameras, 3) uint8."""

    def __init__(self, model: mujoco.MjModel, cameras: Sequence[str], height: int, width: int,
                 *, show_collision: bool = False, shadows: bool = False) -> None:
        self.backend = select_gl_backend()
        self.height, self.width = height, width
        self.cameras = tuple(cameras)
        total_w = width * len(self.cameras)
        # The offscreen buffer must hold all viewports; growing it is harmless for others.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, total_w)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        self._model = model
        if self.backend == "egl" and _FORKED_AFTER_EGL is not None:
            raise _forked_after_egl_error(_FORKED_AFTER_EGL)
        try:
            self._gl = _gl_context_class(self.backend)(total_w, height)
            _register_atexit()
            self._gl.make_current()
            self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
        except mujoco.FatalError as exc:  # e.g. glfw with a DISPLAY that cannot be opened
            raise RuntimeError(f"MUJOCO_GL={self.backend!r} gave no OpenGL context ({exc}); "
                               f"{HEADLESS_HINT}") from None
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        self._scene = mujoco.MjvScene(model, maxgeom=256)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._opt = mujoco.MjvOption()
        self._opt.geomgroup[COLLISION_GROUP] = show_collision
        self._pert = mujoco.MjvPerturb()
        self._cams = []
        for name in self.cameras:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = model.camera(name).id
            self._cams.append(cam)
        # MuJoCo's near plane is a fraction of the scene's extent (~6 cm here): it would cut
        # the jaws out of the wrist camera's view, so close-up cameras get their own.
        extent = max(float(model.stat.extent), 1e-6)
        self._znear = [NEAR_CLIP[name] / extent if name in NEAR_CLIP else None
                       for name in self.cameras]
        self._rects = [mujoco.MjrRect(i * width, 0, width, height)
                       for i in range(len(self.cameras))]
        self._full = mujoco.MjrRect(0, 0, total_w, height)
        self._buf = np.empty((height, total_w, 3), dtype=np.uint8)
        self.texture_versions: dict[int, int] = {}  # see upload_texture
        _LIVE.add(self)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """Return a new (H, W * n_cameras, 3) uint8 frame, cameras left to right."""
        self._make_current()
        m, scn = self._model, self._scene
        default_znear = m.vis.map.znear
        for i, (cam, rect) in enumerate(zip(self._cams, self._rects, strict=True)):
            znear = self._znear[i]
            if znear is not None:
                m.vis.map.znear = znear
            if i:
                mujoco.mjv_updateCamera(m, data, cam, scn)
            else:  # the scene's geoms once per frame; only the camera changes after that
                mujoco.mjv_updateScene(m, data, self._opt, self._pert, cam,
                                       mujoco.mjtCatBit.mjCAT_ALL, scn)
            if znear is not None:
                m.vis.map.znear = default_znear
            mujoco.mjr_render(rect, scn, self._con)
        mujoco.mjr_readPixels(self._buf, None, self._full, self._con)
        return np.flipud(self._buf).copy()

    def upload_texture(self, texid: int, version: int, nearest: bool = False) -> None:
        """Send the model's texture `texid` to the GL context again, unless this `version` of
        its data is there already. `nearest`: sample it without filtering. MuJoCo sets
        trilinear filtering; on a CPU rasteriser (llvmpipe) that made a textured table cost
        18% of a frame, nearest 11%."""
        if self.texture_versions.get(texid) == version:
            return
        self.texture_versions[texid] = version
        self._make_current()
        mujoco.mjr_uploadTexture(self._model, self._con, texid)
        if nearest:
            from OpenGL import GL  # PyOpenGL: mujoco's own GL contexts are built on it

            GL.glBindTexture(GL.GL_TEXTURE_2D, int(self._con.texture[texid]))
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER,
                               GL.GL_NEAREST_MIPMAP_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
            GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def _make_current(self) -> None:
        if self._gl is None:
            if _FORKED_AFTER_EGL is not None:  # a renderer the parent opened, used after fork
                raise _forked_after_egl_error(_FORKED_AFTER_EGL)
            raise RuntimeError("this renderer is closed; create the env (or renderer) again")
        self._gl.make_current()

    def close(self) -> None:
        if self._gl is not None:
            self._con.free()
            self._gl.free()
            self._gl = None

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at shutdown GL libraries may already be gone
            self.close()

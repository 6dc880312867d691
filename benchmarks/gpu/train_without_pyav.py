"""`so101-sim train` on a machine that has OpenCV but no PyAV (the lent GPU image).

    python benchmarks/gpu/train_without_pyav.py --preset cpu --dataset D --out O ...

PyAV's wheel (~35 MB) does not fit the 64 MiB that travels to a lent GPU with the repo and a
dataset, and the trainer only needs it to decode each video once into the frame cache. Where
`import av` fails, a stand-in module decodes with OpenCV's bundled FFmpeg instead (frame i of a
file at time i / fps, which is how `benchmarks/gpu/pack_dataset.py` writes them); every other
use of `av` raises. Prints one line when the stand-in is used. With PyAV present it changes
nothing.
"""

from __future__ import annotations

import atexit
import importlib.machinery
import os
import shutil
import sys
import tempfile
import types
from collections.abc import Iterator
from pathlib import Path

import numpy as np


class _Frame:
    def __init__(self, rgb: np.ndarray, time: float) -> None:
        self._rgb = rgb
        self.time = time

    def to_ndarray(self, format: str = "rgb24") -> np.ndarray:
        if format != "rgb24":
            raise ValueError(f"the OpenCV stand-in for PyAV decodes rgb24 only, not {format!r}")
        return self._rgb


class _Container:
    def __init__(self, path: str) -> None:
        import cv2

        self._cap = cv2.VideoCapture(path)
        if not self._cap.isOpened():
            raise FileNotFoundError(f"{path}: OpenCV could not open this video")
        self._fps = float(self._cap.get(cv2.CAP_PROP_FPS))
        self.streams = types.SimpleNamespace(video=[types.SimpleNamespace(thread_type=None)])

    def __enter__(self) -> _Container:
        return self

    def __exit__(self, *exc: object) -> None:
        self._cap.release()

    def decode(self, stream: object) -> Iterator[_Frame]:
        i = 0
        while True:
            ok, bgr = self._cap.read()
            if not ok:
                return
            yield _Frame(np.ascontiguousarray(bgr[..., ::-1]), i / self._fps)
            i += 1


class _Unavailable:
    """Stands for any other PyAV name: fine in annotations and defaults, an error when used."""

    def __getattr__(self, name: str) -> _Unavailable:
        return self

    def __or__(self, other: object) -> _Unavailable:  # `av.codec.Codec | None` annotations
        return self

    __ror__ = __or__

    def __call__(self, *args: object, **kwargs: object) -> None:
        raise RuntimeError("PyAV is not installed here; only decoding for the frame cache is "
                           "stood in for. Install av to record or write videos")


def _missing(name: str) -> _Unavailable:
    if name.startswith("__"):  # inspect and pickle probe dunders such as __file__
        raise AttributeError(name)
    return _Unavailable()


def stand_in_module() -> types.ModuleType:
    """The OpenCV stand-in for the `av` module (benchmarks/gpu/site_setup.sh installs it as a
    package, so env workers get it too)."""
    module = types.ModuleType("av")
    module.__spec__ = importlib.machinery.ModuleSpec("av", None)  # find_spec("av") works
    module.__version__ = "0+opencv-stand-in"
    module.open = _Container
    module.logging = types.SimpleNamespace(
        WARNING=30, ERROR=40, INFO=20, set_level=lambda level: None,
        restore_default_callback=lambda: None, get_level=lambda: 30)
    module.__getattr__ = _missing
    return module


def write_package(site: str | Path) -> Path:
    """Write the stand-in as an installed `av` package (and its version record) into the
    folder `site`, for a PYTHONPATH on a machine without PyAV: every process that imports
    `av`, env workers too, then gets the stand-in. Returns the package folder."""
    site = Path(site)
    package, meta = site / "av", site / "av-0.0.0.dist-info"
    package.mkdir(parents=True, exist_ok=True)
    meta.mkdir(exist_ok=True)
    (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: av\nVersion: 0.0.0\n")
    (package / "__init__.py").write_text(
        "# PyAV stand-in written by benchmarks/gpu/train_without_pyav.py\n"
        f"import sys\nsys.path.insert(0, {str(Path(__file__).resolve().parent)!r})\n"
        "from train_without_pyav import stand_in_module\n"
        "sys.modules[__name__] = stand_in_module()\n")
    return package


def install_stand_in() -> Path | None:
    """Make `import av` give the OpenCV stand-in, unless PyAV itself imports. Returns the
    temporary folder of its version record (removed when this process exits), else None."""
    try:
        import av  # noqa: F401
        return None
    except ImportError:
        pass
    sys.modules["av"] = stand_in_module()
    # lerobot.datasets asks importlib.metadata for av's version before it imports anything
    folder = Path(tempfile.mkdtemp(prefix="av_stand_in_"))
    owner = os.getpid()  # forked workers inherit the hook; only this process removes it
    atexit.register(lambda: os.getpid() == owner and shutil.rmtree(folder, ignore_errors=True))
    meta = folder / "av-0.0.0.dist-info"
    meta.mkdir()
    (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: av\nVersion: 0.0.0\n")
    sys.path.append(str(meta.parent))
    print("PyAV is missing: the frame cache decodes with OpenCV (benchmarks/gpu/"
          "train_without_pyav.py)", flush=True)
    return folder


def main() -> int:
    install_stand_in()
    from so101_sim.cli import main as cli_main

    sys.argv = ["so101-sim", "train", *sys.argv[1:]]
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())

"""benchmarks/gpu: a packed dataset and the PyAV stand-in give the trainer the frames it expects."""

from __future__ import annotations

import ctypes
import hashlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import tarfile
from multiprocessing import forkserver
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from safetensors.torch import load_file
from script_loader import load_script

from so101_sim.dataset.reader import open_lerobot_dataset
from so101_sim.record import record
from so101_sim.train.frame_cache import decode_camera

GPU = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu"
# Packed at 48x64 from a 96x128 recording. At this size, on some CPUs (seen on AVX-512, not
# on AVX2), libx264's macroblock-tree reads memory it did not initialise, so only --repeatable
# packs have bytes that cannot depend on the process (the last packing test).
SIZE = (48, 64)


def _pack_module():
    # --workers pickles its functions by module name
    return load_script(GPU / "pack_dataset.py", register=True)


@pytest.fixture
def no_fork(monkeypatch: pytest.MonkeyPatch) -> None:
    """--workers must not fork this process: by then pyarrow's and torch's threads run in it
    (Python 3.12 warns of deadlocks). Nor may it start or use the process's fork server, which
    every later pool in the process (the rest of a test session) would get with pack's
    modules instead of its own. Its workers are spawned and import the script by name."""
    def refuse() -> int:
        raise AssertionError("os.fork() called from a multi-threaded process")

    def refuse_server(self) -> None:
        raise AssertionError("pack used the process's fork server")
    monkeypatch.setattr(os, "fork", refuse)
    monkeypatch.setattr(forkserver.ForkServer, "ensure_running", refuse_server)
    monkeypatch.syspath_prepend(str(GPU))


@pytest.fixture(scope="module")
def packed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("gpu")
    record(root / "src", 1, image_size=(96, 128), progress=False)
    (root / "src_videos.json").write_text(json.dumps(_video_digests(root / "src")))
    _pack_module().pack(root / "src", root / "packed", SIZE, crf=14)
    return root / "src", root / "packed"


def _video_digests(folder: Path) -> dict[str, str]:
    return {str(v.relative_to(folder)): hashlib.sha256(v.read_bytes()).hexdigest()
            for v in sorted(folder.glob("videos/**/*.mp4"))}


def test_packing_keeps_the_recording_and_shrinks_the_videos(packed, capsys) -> None:
    src, out = packed
    assert json.loads((out / "meta" / "info.json").read_text()) == \
        json.loads((src / "meta" / "info.json").read_text())  # eval still renders at 96x128
    a, b = open_lerobot_dataset(src), open_lerobot_dataset(out)
    # the parquet files are zstd now, their tables the same, read back through lerobot
    assert {pq.ParquetFile(f).metadata.row_group(0).column(0).compression
            for f in out.rglob("*.parquet")} == {"ZSTD"}
    assert b.hf_dataset.to_pandas().equals(a.hf_dataset.to_pandas())
    for key in a.meta.video_keys:
        before, after = decode_camera(a, key, SIZE), decode_camera(b, key, SIZE)
        assert after.shape == before.shape
        err = np.abs(after.astype(np.int16) - before.astype(np.int16))
        assert err.mean() < 3.0, err.mean()  # crf 14, yuv444p: a few grey levels at most
    videos = sorted(out.glob("videos/**/*.mp4"))
    assert videos and all(v.stat().st_size < w.stat().st_size
                          for v, w in zip(videos, sorted(src.glob("videos/**/*.mp4")),
                                          strict=True))
    with pytest.raises(SystemExit, match="exists; remove it"):
        _pack_module().pack(src, out, SIZE, crf=14)


def test_packing_in_parallel_can_drop_what_the_trainer_does_not_read(packed, tmp_path,
                                                                    no_fork) -> None:
    """--workers re-encodes files in processes as close to the source as one process does
    (the same bytes with --repeatable: the next test); --drop-columns removes a feature from
    the tables and info.json and refuses one the trainer reads."""
    src, _ = packed
    out = tmp_path / "packed2"
    _pack_module().pack(src, out, SIZE, crf=14, workers=2,
                        drop=("initial_cube_pose", "episode_seed"))
    before = json.loads((src / "meta" / "info.json").read_text())
    after = json.loads((out / "meta" / "info.json").read_text())
    assert set(before["features"]) - set(after["features"]) == {"initial_cube_pose",
                                                                "episode_seed"}
    a, b = open_lerobot_dataset(src), open_lerobot_dataset(out)
    assert "initial_cube_pose" not in b.hf_dataset.column_names
    for key in ("observation.state", "action", "index"):
        assert np.array_equal(np.asarray(b.hf_dataset.with_format("numpy")[key]),
                              np.asarray(a.hf_dataset.with_format("numpy")[key]))
    assert _video_digests(src) == json.loads((src.parent / "src_videos.json").read_text()), \
        "the recording's videos changed after record() returned"
    for key in a.meta.video_keys:  # each worker's re-encoding is as close as one process's
        source = decode_camera(a, key, SIZE).astype(np.int16)
        err = np.abs(decode_camera(b, key, SIZE).astype(np.int16) - source)
        assert err.mean() < 3.0, err.mean()
    with pytest.raises(SystemExit, match="--drop-columns action: expected one of"):
        _pack_module().pack(src, tmp_path / "bad", SIZE, crf=14, drop=("action",))


def _scribble_heap(seed: int) -> None:
    """Leave freed malloc blocks full of bytes no other process has, as a long-lived process
    (a pytest worker, a notebook) does."""
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    rng = random.Random(seed)
    blocks = []
    for _ in range(2000):
        n = rng.choice([64, 256, 1024, 4096, 16384, 65536])
        blocks.append(libc.malloc(n))
        ctypes.memset(blocks[-1], rng.randrange(1, 256), n)
    for block in blocks:
        libc.free(ctypes.c_void_p(block))


def test_repeatable_packing_gives_the_same_bytes_in_any_process(packed, tmp_path,
                                                                no_fork) -> None:
    """--repeatable: one process with a scribbled heap and two --workers processes (spawned,
    heaps of their own) write the same bytes (by default, on some CPUs, x264's
    macroblock-tree makes them depend on the heap)."""
    src, _ = packed
    _scribble_heap(1)
    _pack_module().pack(src, tmp_path / "one", SIZE, crf=14, repeatable=True)
    _scribble_heap(2)
    _pack_module().pack(src, tmp_path / "two", SIZE, crf=14, workers=2, repeatable=True)
    one, two = _video_digests(tmp_path / "one"), _video_digests(tmp_path / "two")
    assert len(one) == 2 and one == two, "same source, other bytes"


_WITHOUT_PYAV = """
import sys
import numpy as np
class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "av" or name.startswith("av."):
            raise ImportError("PyAV hidden for this test")
sys.meta_path.insert(0, Block())
sys.path.insert(0, sys.argv[1])
import train_without_pyav
print("stand-in folder:", train_without_pyav.install_stand_in())
from so101_sim.dataset.reader import open_lerobot_dataset
from so101_sim.train.frame_cache import decode_camera
ds = open_lerobot_dataset(sys.argv[2])
size = tuple(int(v) for v in sys.argv[4].split("x"))
np.save(sys.argv[3], decode_camera(ds, ds.meta.video_keys[0], size))
"""


def test_the_stand_in_decodes_what_pyav_decodes(packed, tmp_path: Path) -> None:
    """Without PyAV, the trainer's frame cache reads the packed videos through OpenCV and gets
    the same frames, bit for bit, in the same order."""
    _, out = packed
    got = tmp_path / "frames.npy"
    run = subprocess.run([sys.executable, "-c", _WITHOUT_PYAV, str(GPU), str(out), str(got),
                          "{}x{}".format(*SIZE)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "PyAV is missing: the frame cache decodes with OpenCV" in run.stdout
    folder = Path(run.stdout.split("stand-in folder: ")[1].split()[0])
    assert folder.name.startswith("av_stand_in_") and not folder.exists()  # none left in /tmp
    ds = open_lerobot_dataset(out)
    expected = decode_camera(ds, ds.meta.video_keys[0], SIZE)
    np.testing.assert_array_equal(np.load(got), expected)


def test_with_pyav_present_the_stand_in_steps_aside() -> None:
    sys.path.insert(0, str(GPU))
    try:
        import train_without_pyav
    finally:
        sys.path.remove(str(GPU))
    import av

    assert train_without_pyav.install_stand_in() is None
    assert sys.modules["av"] is av and hasattr(av, "VideoFrame")


_STAND_IN_PACKAGE = """
import importlib.metadata
import av
from so101_sim.harness.policies.lerobot import LeRobotPolicy
print(av.__version__, importlib.metadata.version("av"))
policy = LeRobotPolicy(__import__("sys").argv[1], task_description="pick")
print(type(policy.policy).__name__)
"""


def test_the_stand_in_package_lets_eval_load_a_policy(tmp_path: Path) -> None:
    """site_setup.sh's PyAV stand-in, written as a package ahead of the real av on the path (as
    on the GPU image, which has none): lerobot's datasets module sees an installed av, and the
    harness loads a Diffusion checkpoint through lerobot."""
    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_policy import make_tiny_diffusion_checkpoint

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "tiny", input_size=(48, 64),
                                          dataset_image_size=(96, 128))
    train_without_pyav = load_script(GPU / "train_without_pyav.py")
    package = train_without_pyav.write_package(tmp_path / "site")
    assert (package / "__init__.py").is_file()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path / "site"), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-c", _STAND_IN_PACKAGE, str(ckpt)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.splitlines()  # lerobot prints a line of its own between ours
    assert lines[0] == "0+opencv-stand-in 0.0.0" and lines[-1] == "DiffusionPolicy"


def test_two_calls_join_the_halves_and_send_back_fp16_policies(packed, tmp_path: Path) -> None:
    """finetune_from_stash.sh (call 2) joins the half call 1 stashed with the half it carries,
    trains from the shipped suite weights and, beside it, a second run from scratch, and leaves
    each last policy and the first run's MID policy in $OUT as fp16 tars (on the CPU, 2 steps)."""
    src, one = packed
    stash, half, out = tmp_path / "stash", tmp_path / "B", tmp_path / "out"
    camera = sorted((one / "videos").iterdir())[0].name
    shutil.copytree(one / "videos" / camera, stash / "A" / "videos" / camera)  # call 1's half
    shutil.copytree(one, half, ignore=lambda d, names: [camera] if d.endswith("videos") else [])
    env = {**os.environ, "STASH": str(stash), "OUT": str(out), "RUNS": str(tmp_path / "runs"),
           "DEVICE": "cpu", "PY": sys.executable}
    done = subprocess.run(["bash", str(GPU / "finetune_from_stash.sh"), str(half), "300",
                           "t:cpu_ft:4:2", "2", "s:cpu:4:2::scratch"], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    joined = stash / "data"
    assert {p.name for p in (joined / "videos").iterdir()} == \
        {p.name for p in (src / "videos").iterdir()}
    assert (joined / "meta" / "info.json").is_file()
    assert "=== s: preset cpu, batch 4, 2 steps" in done.stdout and "from scratch" in done.stdout
    assert "a call returns about two" in done.stdout  # three policies: one will not come back
    for name in ("t", "mid2", "s"):
        parts = sorted(out.glob(f"{name}.tar.*"))
        assert parts, done.stdout[-2000:]
        unpacked = tmp_path / f"un_{name}"
        unpacked.mkdir()
        blob = b"".join(p.read_bytes() for p in parts)
        with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
            tar.extractall(unpacked, filter="data")
        weights = load_file(unpacked / "model.safetensors")
        assert {v.dtype for v in weights.values() if v.is_floating_point()} == {torch.float16}

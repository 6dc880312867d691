"""Shrink a LeRobotDataset so it travels to a lent GPU machine (64 MiB per call, repo included).

    .venv/bin/python benchmarks/gpu/pack_dataset.py SRC OUT [--size 60x80] [--crf 14] [--workers 2]
        [--drop-columns action_executed,initial_cube_pose,episode_seed] [--repeatable]

The policy only ever sees frames resized to its input size, so each camera video is decoded
here exactly as the trainer's frame cache decodes it (PyAV, `resize_frames`), and re-encoded
at that size (libx264, yuv444p: no chroma subsampling at 60x80, where the cube is ~4 px wide).
On the GPU machine the trainer's resize is then the identity. `meta/info.json` keeps the
recorded size, because that is the size evaluation must render at to match the recording.
Parquet files keep their tables and are re-compressed with zstd (about 30% smaller than
lerobot's default; pyarrow reads either). `--drop-columns` removes per-frame features the
trainer never reads (a 600-demo tidy recording: 29.9 -> 19.2 MB of tables). Prints the size
and the per-pixel error of the re-encoding.

The bytes of a pack are not always repeatable by default: on some CPUs x264's
macroblock-tree reads memory it never initialised at these frame sizes, so the same frames
encode differently in a process whose heap holds other data (at 60x80 on an AVX-512 EPYC,
11 distinct files from 12 processes with scribbled heaps, against 1 from 12 with the tree off;
on an AVX2 EPYC one set of bytes either way). `--repeatable` turns the tree off: the same
bytes in any process, and so with `--workers`, for ~12% more bytes at equal error (crf 18
against 14; benchmarks/README.md, "gpu/").
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq

from so101_sim.utils.image_pipeline import resize_frames

# what `so101_sim.train.demos.load_demos` and LeRobotDataset's own indexing need
TRAINER_READS = frozenset({"observation.state", "action", "timestamp", "frame_index",
                           "episode_index", "index", "task_index"})


def _frames(path: Path, size: tuple[int, int]) -> np.ndarray:
    with av.open(str(path)) as container:
        raw = [f.to_ndarray(format="rgb24") for f in container.decode(container.streams.video[0])]
    return resize_frames(np.stack(raw), size).numpy().transpose(0, 2, 3, 1).copy()


def _encode(frames: np.ndarray, path: Path, fps: int, crf: int, repeatable: bool) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv444p"
        # one encoder thread: no thread scheduling inside x264. That alone is not enough for
        # the same bytes: on some CPUs the macroblock-tree reads uninitialised memory at small
        # sizes (the module docstring), so --repeatable turns it off.
        options = {"crf": str(crf), "preset": "slow", "threads": "1"}
        if repeatable:
            options["x264-params"] = "mbtree=0"
        stream.options = options
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def _pack_video(job: tuple[Path, Path, tuple[int, int], int, int, bool],
                ) -> tuple[int, float, np.ndarray]:
    """Re-encode one video; returns its frame count, size in MB and per-pixel errors."""
    video, target, size, fps, crf, repeatable = job
    target.parent.mkdir(parents=True, exist_ok=True)
    frames = _frames(video, size)
    _encode(frames, target, fps, crf, repeatable)
    with av.open(str(target)) as container:
        back = np.stack([f.to_ndarray(format="rgb24")
                         for f in container.decode(container.streams.video[0])])
    if back.shape != frames.shape:
        raise SystemExit(f"{target}: decoded {back.shape}, encoded {frames.shape}")
    error = np.abs(back.astype(np.int16) - frames.astype(np.int16)).ravel()
    # mean and 99th percentile from a strided subsample: a 600-demo set's errors are GBs
    return len(frames), target.stat().st_size / 1e6, error[:: max(1, error.size // 2_000_000)]


def _drop_features(out: Path, drop: tuple[str, ...]) -> None:
    """Remove per-frame features the trainer never reads from info.json (the tables follow)."""
    info_path = out / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    for name in drop:
        if name in TRAINER_READS or name not in info["features"]:
            raise SystemExit(f"--drop-columns {name}: expected one of "
                             f"{sorted(set(info['features']) - TRAINER_READS)} (the features "
                             "the trainer does not read); leave the others in")
    for name in drop:
        del info["features"][name]
    info_path.write_text(json.dumps(info, indent=4))


def pack(src: Path, out: Path, size: tuple[int, int], crf: int, fps: int = 30,
         workers: int = 1, drop: tuple[str, ...] = (), repeatable: bool = False) -> None:
    if not (src / "meta" / "info.json").is_file():
        raise SystemExit(f"{src}: no meta/info.json; expected a LeRobotDataset folder "
                         "(so101-sim record --out)")
    if out.exists():
        raise SystemExit(f"{out} exists; remove it or pick another OUT")
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("*.mp4"))
    if drop:
        _drop_features(out, drop)
    for table in out.rglob("*.parquet"):
        columns = pq.read_table(table)
        if drop and table.is_relative_to(out / "data"):  # the per-frame tables
            columns = columns.drop_columns(list(drop))
        pq.write_table(columns, table, compression="zstd", compression_level=19)
    videos = sorted(src.glob("videos/**/*.mp4"))
    jobs = [(video, out / video.relative_to(src), size, fps, crf, repeatable) for video in videos]
    if workers > 1:
        # Never fork this process: pyarrow's and torch's threads are running by now, and a
        # forked child that needs a lock one of them held hangs. Spawned children start clean,
        # and leave this process's fork server alone: started here with these modules, it
        # would serve every later pool in the process (a test session's) without theirs.
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            results = list(pool.map(_pack_video, jobs))
    else:
        results = [_pack_video(job) for job in jobs]
    errors = []
    for video, (frames, size_mb, error) in zip(videos, results, strict=True):
        errors.append(error)
        print(f"{video.relative_to(src)}: {frames} frames, {size_mb:.2f} MB")
    err = np.concatenate(errors)
    total = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"{out}: {total / 1e6:.1f} MB; re-encoding error per pixel and channel: mean "
          f"{err.mean():.2f}, 99th percentile {np.percentile(err, 99):.0f}, max {err.max()} "
          "grey levels")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("src", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", default="60x80", help="HxW the policy reads (default 60x80)")
    parser.add_argument("--crf", type=int, default=14, help="libx264 crf (default 14)")
    parser.add_argument("--workers", type=int, default=1,
                        help="video files re-encoded at once, one process each (default 1)")
    parser.add_argument("--drop-columns", default="",
                        help="comma-separated per-frame features the trainer does not read "
                             "(e.g. action_executed,initial_cube_pose,episode_seed), removed "
                             "from the tables and info.json to fit a large recording")
    parser.add_argument("--repeatable", action="store_true",
                        help="the same bytes from any process (x264's macroblock-tree off: "
                             "~12%% more bytes at equal error, with --crf 4 higher)")
    args = parser.parse_args()
    h, w = (int(v) for v in args.size.lower().split("x"))
    drop = tuple(c for c in args.drop_columns.split(",") if c)
    pack(args.src, args.out, (h, w), args.crf, workers=args.workers, drop=drop,
         repeatable=args.repeatable)


if __name__ == "__main__":
    main()

"""Shrink a LeRobotDataset so it travels to a lent GPU machine (64 MiB per call, repo included).

    .venv/bin/python benchmarks/gpu/pack_dataset.py SRC OUT [--size 60x80] [--crf 14]

The policy only ever sees frames resized to its input size, so each camera video is decoded
here exactly as the trainer's frame cache decodes it (PyAV, `resize_frames`), and re-encoded
at that size (libx264, yuv444p: no chroma subsampling at 60x80, where the cube is ~4 px wide).
On the GPU machine the trainer's resize is then the identity. `meta/info.json` keeps the
recorded size, because that is the size evaluation must render at to match the recording.
Parquet files keep their tables and are re-compressed with zstd (about 30% smaller than
lerobot's default; pyarrow reads either). Prints the size and the per-pixel error of the
re-encoding.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq

from so101_sim.utils.image_pipeline import resize_frames


def _frames(path: Path, size: tuple[int, int]) -> np.ndarray:
    with av.open(str(path)) as container:
        raw = [f.to_ndarray(format="rgb24") for f in container.decode(container.streams.video[0])]
    return resize_frames(np.stack(raw), size).numpy().transpose(0, 2, 3, 1).copy()


def _encode(frames: np.ndarray, path: Path, fps: int, crf: int) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv444p"
        stream.options = {"crf": str(crf), "preset": "slow"}
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def pack(src: Path, out: Path, size: tuple[int, int], crf: int, fps: int = 30) -> None:
    if not (src / "meta" / "info.json").is_file():
        raise SystemExit(f"{src}: no meta/info.json; expected a LeRobotDataset folder "
                         "(so101-sim record --out)")
    if out.exists():
        raise SystemExit(f"{out} exists; remove it or pick another OUT")
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("*.mp4"))
    for table in out.rglob("*.parquet"):
        pq.write_table(pq.read_table(table), table, compression="zstd", compression_level=19)
    errors = []
    for video in sorted(src.glob("videos/**/*.mp4")):
        target = out / video.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        frames = _frames(video, size)
        _encode(frames, target, fps, crf)
        with av.open(str(target)) as container:
            back = np.stack([f.to_ndarray(format="rgb24")
                             for f in container.decode(container.streams.video[0])])
        if back.shape != frames.shape:
            raise SystemExit(f"{target}: decoded {back.shape}, encoded {frames.shape}")
        errors.append(np.abs(back.astype(np.int16) - frames.astype(np.int16)).ravel())
        size_mb = target.stat().st_size / 1e6
        print(f"{video.relative_to(src)}: {len(frames)} frames, {size_mb:.2f} MB")
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
    args = parser.parse_args()
    h, w = (int(v) for v in args.size.lower().split("x"))
    pack(args.src, args.out, (h, w), args.crf)


if __name__ == "__main__":
    main()

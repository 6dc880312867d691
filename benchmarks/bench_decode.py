"""PyAV vs torchcodec decoding one camera mp4 of a recorded dataset, as the trainer's frame cache.

    taskset -c 1 .venv/bin/python benchmarks/bench_decode.py DATASET [--frames 3000]

The frame cache (`so101_sim/frame_cache.py`) decodes every frame of each video once, in order,
and resizes it with `resize_frames`. This times that sequential decode to uint8 RGB with both
decoders (the same frames; the resize is shared and timed separately), alternating the two
`--repeats` times so that a neighbour's load hits both alike. Frames are dropped chunk by
chunk (memory stays at one chunk). torchcodec needs FFmpeg 4-8 shared
libraries (e.g. `apt-get install ffmpeg`, or unpacked debs on LD_LIBRARY_PATH); without them
only PyAV is timed.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import av
import numpy as np

CHUNK = 256  # frames per batch, as the frame cache


def chunks_pyav(path: Path, n: int) -> Iterator[np.ndarray]:
    """The frame cache's loop: thread_type AUTO, rgb24 ndarrays, first `n` frames, in chunks."""
    pending: list[np.ndarray] = []
    done = 0
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        for frame in container.decode(stream):
            pending.append(frame.to_ndarray(format="rgb24"))
            done += 1
            if len(pending) == CHUNK or done == n:
                yield np.stack(pending)
                pending.clear()
            if done == n:
                return


def chunks_torchcodec(path: Path, n: int) -> Iterator[np.ndarray]:
    """torchcodec's sequential batch API (CHW uint8), in chunks of CHUNK frames."""
    from torchcodec.decoders import VideoDecoder

    dec = VideoDecoder(str(path), device="cpu", seek_mode="approximate")
    for start in range(0, n, CHUNK):
        yield dec.get_frames_in_range(start, min(start + CHUNK, n)).data.numpy()


def timed(chunks: Iterator[np.ndarray],
          size: tuple[int, int] | None) -> tuple[float, float, float, np.ndarray]:
    """(decode wall s, decode CPU s, resize wall s, first chunk as CHW) for one pass; frames
    are dropped as they go. CPU seconds (all threads of this process) are the steadier number
    on a core shared with other jobs."""
    from so101_sim.utils.image_pipeline import resize_frames

    decode_s = decode_cpu = resize_s = 0.0
    first = None
    t0, c0 = time.perf_counter(), time.process_time()
    for frames in chunks:
        t1, c1 = time.perf_counter(), time.process_time()
        decode_s += t1 - t0
        decode_cpu += c1 - c0
        if size is not None:
            resize_frames(frames, size)
        t0, c0 = time.perf_counter(), time.process_time()
        resize_s += t0 - t1
        if first is None:
            first = frames if frames.shape[1] == 3 else frames.transpose(0, 3, 1, 2)
    return decode_s, decode_cpu, resize_s, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="LeRobotDataset folder (so101-sim record)")
    parser.add_argument("--camera", default="front")
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--size", default="60x80", help="resize target (the cpu preset's)")
    parser.add_argument("--no-resize", action="store_true", help="time decoding alone")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads for the resize (default 1: spinning OpenMP workers "
                             "would compete with the decoder on a pinned core)")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    size = tuple(int(v) for v in args.size.split("x"))

    video = next((args.dataset / "videos" / f"observation.images.{args.camera}").rglob("*.mp4"))
    decoders = {"pyav": chunks_pyav, "torchcodec": chunks_torchcodec}
    try:
        import torchcodec.decoders  # noqa: F401
    except (ImportError, OSError, RuntimeError):
        del decoders["torchcodec"]
        print("torchcodec cannot load here (no FFmpeg 4-8 shared libraries): PyAV only")
    with av.open(str(video)) as c:
        s = c.streams.video[0]
        print(f"{video}: {s.codec_context.name} {s.height}x{s.width}, the first {args.frames} "
              f"frames, {args.repeats} alternating passes per decoder, resize to {args.size}")
    runs: dict[str, list[tuple[float, float, float]]] = {name: [] for name in decoders}
    firsts = {}
    for _ in range(args.repeats):
        for name, fn in decoders.items():
            dec_s, dec_cpu, res_s, firsts[name] = timed(fn(video, args.frames),
                                                        None if args.no_resize else size)
            runs[name].append((dec_s, dec_cpu, res_s))
    if len(firsts) == 2:
        same = np.array_equal(firsts["pyav"], firsts["torchcodec"])
        print(f"first {CHUNK} frames identical between the decoders: {same}")
    print("| decoder | decode wall s (best) | frames/s | decode CPU s (best) | CPU frames/s "
          "| decode + resize wall s (best) | decode wall runs (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, rs in runs.items():
        best = min(d for d, _, _ in rs)
        cpu = min(c for _, c, _ in rs)
        both = min(d + r for d, _, r in rs)
        print(f"| {name} | {best:.2f} | {args.frames / best:.0f} | {cpu:.2f} | "
              f"{args.frames / cpu:.0f} | {both:.2f} | "
              + ", ".join(f"{d:.2f}" for d, _, _ in rs) + " |")


if __name__ == "__main__":
    main()

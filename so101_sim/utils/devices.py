"""Which torch device and precision `train` and `eval` run on: `--device auto|cpu|cuda|mps`.

`auto` takes CUDA, then Apple's MPS, then the CPU. Precision `auto` takes bfloat16 autocast
where it was measured faster: CPUs with AMX or AVX512-BF16 (1.4x per training step here). On
CUDA it takes fp32: at the presets' batch sizes an H200 step is launch-bound and autocast's
casts made it slower (seed 0.029 s fp32 against 0.036 s bf16, cpu 0.032 against 0.041, act
0.035 against 0.034; at batch 256 equal or slower too; the real trainer 1.2x faster in fp32;
`benchmarks/README.md`, gpu_check.sh). Weights, optimiser state and EMA stay fp32 either way.
torch is imported lazily: `import so101_sim` stays light.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from so101_sim.utils.text import counted

DEVICES = ("auto", "cpu", "cuda", "mps")
PRECISIONS = ("auto", "fp32", "bf16")


def resolve_device(name: str = "auto") -> str:
    """A concrete torch device type for `name`; refuses one this machine does not have."""
    import torch

    if name not in DEVICES:
        raise ValueError(f"device={name!r} is invalid; expected one of {DEVICES}")
    has_mps = bool(getattr(torch.backends, "mps", None)) and torch.backends.mps.is_available()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "mps" if has_mps else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: torch sees no CUDA GPU here (torch "
                         f"{torch.__version__}); use --device auto or cpu, or install a CUDA "
                         "build of torch on a machine with an NVIDIA GPU")
    if name == "mps" and not has_mps:
        raise ValueError("--device mps: Apple's Metal backend is not available here; use "
                         "--device auto or cpu")
    return name


def cpu_has_fast_bf16() -> bool:
    """True on x86 CPUs with AMX-BF16 or AVX512-BF16 (read from /proc/cpuinfo)."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "amx_bf16" in flags or "avx512_bf16" in flags


def slow_bf16_note(precision: str, device: str) -> str | None:
    """One line when bf16 autocast is asked for on a CPU without native bf16, where it is
    emulated: an 8-row forward of the shipped policy took 14x as long as in fp32 on an
    AVX2 EPYC (7.0 s against 0.49 s, one thread, interleaved)."""
    if precision != "bf16" or device != "cpu" or cpu_has_fast_bf16():
        return None
    return ("note: this CPU has no AVX512-BF16 or AMX, so bf16 autocast is emulated: many "
            "times slower than fp32 (14x per forward on an AVX2 EPYC); --precision fp32 is "
            "the fast choice here")


def resolve_precision(precision: str, device: str) -> str:
    """`fp32` or `bf16` for a concrete `device`; `auto` picks bf16 where it is faster."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision={precision!r} is invalid; expected one of {PRECISIONS}")
    if precision != "auto":
        return precision
    if device == "cuda":
        return "fp32"  # measured faster on an H200 at the presets' batch sizes (see above)
    if device == "cpu":
        return "bf16" if cpu_has_fast_bf16() else "fp32"
    return "fp32"  # mps: bf16 autocast depends on the macOS version; stay safe


def cpu_count() -> int:
    """CPU cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


#: Memory one local eval env worker takes: 120 MB PSS each, measured for 8 workers rendering
#: two cameras at 240x320 for the shipped policy (AVX2 EPYC, 2026-12-03), rounded up for
#: video and rollout encoding.
WORKER_MB = 160


#: Memory one local `record` worker takes: at most 249 MB PSS for 4 workers recording front and
#: side at 480x640 with h264, 278 MB with the wrist camera too (AVX2 EPYC, 2026-12-03), rounded
#: up. A larger --image-size takes more.
RECORD_WORKER_MB = 320


def available_mb() -> int | None:
    """MemAvailable from /proc/meminfo in MB (None where there is none)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) // 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def workers_that_fit(n: int, log: Callable[[str], None] = print, *, mb_each: int = WORKER_MB,
                     command: str = "eval", unit: str = "env workers",
                     same: str = "the actions of each seed are the same for any --n-envs") -> int:
    """`n` local workers, or as many as the available memory holds at `mb_each` MB each
    (leaving 1 GB), with one line saying so: 200 workers on a small machine were an
    out-of-memory kill. `same` says why fewer change no result."""
    free = available_mb()
    if free is None:
        return n
    fit = max(1, (free - 1024) // mb_each)
    if fit >= n:
        return n
    log(f"so101-sim {command}: {n} {unit} would take about {n * mb_each / 1024:.1f} GB "
        f"({mb_each} MB each) and {free / 1024:.1f} GB is available: running {fit} ({same})")
    return fit


def eval_policy_threads(asked: int | None = None, log: Callable[[str], None] = print) -> int:
    """Torch threads for policy forwards during `eval` on CPU: `asked` (--threads, with
    `threads_note`), else half the cores, at least one.

    The env workers render on the other half. On 2 cores this is one thread, which keeps a
    16-episode eval as fast as torch's default (2 threads) on an idle machine and stops it
    from slowing down 1.5-1.8x when another process takes a core: a 2-thread OpenMP pool waits
    at every barrier for the thread that lost its core (benchmarks/bench_busy.py). It depends
    on the machine only, never on the number of envs, so results stay K-independent.
    """
    if asked:  # 0 or None: the default, as before
        if note := threads_note(asked, "eval"):
            log(note)
        return asked
    return max(1, cpu_count() // 2)


def threads_note(n: int | None, command: str) -> str | None:
    """One line when --threads `n` is more than the cores this process may use: such an
    OpenMP pool waits on threads that have no core (`train --threads 8` on 2 cores took 34x as
    long a step as `--threads 2`, 0.8 against 27.4 samples/s). The count is kept as asked:
    a fixed one is what makes a run bitwise repeatable on another machine."""
    cores = cpu_count()
    if n is None or n <= cores:
        return None
    return (f"so101-sim {command}: note: --threads {n} is more than the "
            f"{counted(cores, 'CPU core')} this process can use, so torch's threads wait on each "
            "other (a training step took 34x as long with 8 threads on 2 cores); "
            f"--threads {cores} or fewer, or leave it out")


@contextmanager
def torch_threads(n: int | None) -> Iterator[int | None]:
    """Run the block with `n` torch CPU threads (None: leave torch alone), then restore.

    Does nothing unless torch is already imported: a policy that never loaded torch (the
    expert) must not pay for importing it.
    """
    torch = sys.modules.get("torch")
    if n is None or torch is None:
        yield None
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(before)

"""Keep freed tensor memory in the process instead of handing it back to the kernel.

glibc's malloc serves blocks above its mmap threshold with fresh ``mmap`` pages and returns
them on ``free``, and trims the heap's top beyond its trim threshold. A forward or training step
allocates and frees the same multi-MB activations every call, so each call page-faults them in
again: 4,950 minor faults per 8-row DDIM-10 forward of the shipped policy here, none once the
memory is kept, and 4% off that forward (benchmarks/README.md, "heap"). The allocation pattern
changes, the arithmetic does not: results are bit for bit the same.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from collections.abc import Callable

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc caps the mmap threshold at 32 MB on 64-bit (HEAP_MAX_SIZE / 2); larger blocks still map.
_MMAP_THRESHOLD = 32 << 20
_TRIM_THRESHOLD = 1 << 30

_done: bool | None = None


def keep_freed_memory(log: Callable[[str], None] = print) -> bool:
    """Raise glibc's mmap and trim thresholds for this process (once); False off glibc.

    Off glibc (macOS, musl) nothing changes and ``log`` gets one line saying so.
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    name = ctypes.util.find_library("c") if sys.platform.startswith("linux") else None
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        mallopt = None
    if mallopt is not None:
        _done = bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
                     and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
    if not _done:
        log("so101-sim: note: no glibc mallopt here; large tensors are page-faulted in on "
            "every step (slower, same results)")
    return _done

"""bench_eval's floor line: the busy core-seconds it reads from /proc/stat count real work."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_eval import CORES, busy_core_s, floor_line

pytestmark = pytest.mark.skipif(not Path("/proc/stat").exists(), reason="needs /proc/stat")


def steal_core_s() -> float:
    """Time the hypervisor took from this machine's cores (not counted as busy)."""
    return int(Path("/proc/stat").read_text().split()[8]) / os.sysconf("SC_CLK_TCK")


def test_busy_core_seconds_count_at_least_this_process_cpu_time():
    """Whatever else runs, the machine's busy time covers this process's own work."""
    tick = 1 / os.sysconf("SC_CLK_TCK")
    b0, s0, c0 = busy_core_s(), steal_core_s(), time.process_time()
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    cpu = time.process_time() - c0
    # A process's CPU time may include what the hypervisor stole while it ran.
    busy = busy_core_s() - b0 + steal_core_s() - s0
    # /proc/stat counts in ticks, per core: allow one tick of rounding on each.
    assert busy >= cpu - 2 * tick * CORES
    assert cpu >= 0.3


def test_the_floor_spreads_the_work_over_the_cores_this_process_may_use():
    assert len(os.sched_getaffinity(0)) == CORES
    line = floor_line(10.0 * CORES, 12.0)
    assert f"at least 10.0 s on {CORES} cores" in line and "over the 12.0 s" in line

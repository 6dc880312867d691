"""Thread choices for a busy machine: the trainer's adaptive thread count (fed synthetic step
times, so the test does not depend on this machine's load) and eval's fixed default."""

from __future__ import annotations

import torch

from so101_sim.devices import AdaptiveThreads


def _drive(tuner: AdaptiveThreads, cost: dict[int, float], steps: int, start: int = 0) -> int:
    """Run `steps` fake steps whose duration depends only on the thread count in force."""
    for step in range(start + 1, start + steps + 1):
        tuner.after_step(step, cost[torch.get_num_threads()])
    return start + steps


def test_adaptive_threads_follow_the_faster_setting():
    before = torch.get_num_threads()
    try:
        tuner = AdaptiveThreads(cores=2, every=50, probe=3, first=5)
        assert tuner.candidates == [2, 1] and torch.get_num_threads() == 2
        idle = {2: 0.33, 1: 0.55}
        busy = {2: 0.90, 1: 0.55}  # a neighbour took a core: the 2-thread pool stalls
        step = _drive(tuner, idle, 20)
        assert tuner.current == 2 and tuner.best_s == 0.33
        # the neighbour starts: the slowdown triggers a probe before `every` steps pass
        step = _drive(tuner, busy, 15, step)
        assert tuner.current == 1 and tuner.best_s == 0.55 and step < 5 + 50
        # the neighbour leaves: the periodic probe goes back to two threads
        step = _drive(tuner, idle, 60, step)
        assert tuner.current == 2 and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_one_core_has_nothing_to_choose():
    before = torch.get_num_threads()
    try:
        tuner = AdaptiveThreads(cores=1, first=1)
        _drive(tuner, {1: 0.5}, 10)
        assert tuner.candidates == [1] and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_probes_thin_out_while_the_answer_holds():
    before = torch.get_num_threads()
    try:
        tuner = AdaptiveThreads(cores=2, every=100, probe=3, first=5)
        one_thread_steps = 0
        for step in range(1, 3001):
            tuner.after_step(step, {2: 0.33, 1: 0.55}[torch.get_num_threads()])
            one_thread_steps += torch.get_num_threads() == 1
        # probes after 100, 200, 400, then every 400 steps: ~10 probes of 4 one-thread steps,
        # where a fixed 100-step period would spend 120
        assert tuner.current == 2 and 0 < one_thread_steps <= 48
    finally:
        torch.set_num_threads(before)

"""Thread choices for a busy machine: the trainer's adaptive thread count, fed synthetic step
times or loads where the answer must not depend on this machine's load, and a real neighbour
process where it reads /proc/stat."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
import torch

from so101_sim.train.threads import AdaptiveThreads, BatchParts, CpuShare, split_batch
from so101_sim.utils.devices import cpu_count


def _drive(tuner: AdaptiveThreads, cost: dict[int, float], steps: int, start: int = 0) -> int:
    """Run `steps` fake steps whose duration depends only on the thread count in force."""
    for step in range(start + 1, start + steps + 1):
        tuner.after_step(step, cost[torch.get_num_threads()])
    return start + steps


def test_adaptive_threads_follow_the_faster_setting():
    before = torch.get_num_threads()
    try:
        tuner = AdaptiveThreads(cores=2, every=50, probe=3, first=5, sense=False)
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
        tuner = AdaptiveThreads(cores=1, first=1, sense=False)
        _drive(tuner, {1: 0.5}, 10)
        assert tuner.candidates == [1] and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_probes_thin_out_while_the_answer_holds():
    before = torch.get_num_threads()
    try:
        tuner = AdaptiveThreads(cores=2, every=100, probe=3, first=5, sense=False)
        one_thread_steps = 0
        for step in range(1, 3001):
            tuner.after_step(step, {2: 0.33, 1: 0.55}[torch.get_num_threads()])
            one_thread_steps += torch.get_num_threads() == 1
        # probes after 100, 200, 400, then every 400 steps: ~10 probes of 4 one-thread steps,
        # where a fixed 100-step period would spend 120
        assert tuner.current == 2 and 0 < one_thread_steps <= 48
    finally:
        torch.set_num_threads(before)


class _FakeShare:
    """Stands in for CpuShare: reports whatever load the test sets."""

    since = 0.0
    load = 0.0

    def others(self) -> float:
        return self.load


def test_sensed_load_sets_the_threads_that_fit():
    before = torch.get_num_threads()
    try:
        # idle: one pool over all cores; any neighbour: one part per core, one thread each
        for cores, load, want in [(2, 0.0, (2, 1)), (2, 0.2, (2, 1)), (2, 0.7, (1, 2)),
                                  (2, 1.9, (1, 2)), (4, 1.0, (1, 4)), (16, 3.0, (1, 8))]:
            tuner = AdaptiveThreads(cores=cores, window_s=0.0)
            tuner.share = _FakeShare()
            tuner.share.load = load
            tuner.after_step(1, 0.3)
            assert (tuner.current, tuner.parts) == want, (cores, load)
            assert torch.get_num_threads() == want[0]
        tuner.share.load = 0.0  # the neighbour left
        tuner.after_step(2, 0.3)
        assert (tuner.current, tuner.parts) == (16, 1)
    finally:
        torch.set_num_threads(before)


def test_batch_parts_sum_to_the_whole_batch_gradient():
    """Parts of uneven size in threads give the whole batch's loss and gradient."""
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
    batch = {"x": torch.randn(10, 5), "y": torch.randn(10, 2), "task": "pick"}

    def loss_fn(part: dict) -> torch.Tensor:
        assert part["task"] == "pick"  # non-tensor entries pass through
        return torch.nn.functional.mse_loss(model(part["x"]), part["y"])

    whole = loss_fn(batch)
    whole.backward()
    whole = float(whole.detach())
    want = [p.grad.clone() for p in model.parameters()]
    runner = BatchParts()
    try:
        for parts in (2, 3, 10):
            model.zero_grad(set_to_none=True)
            got = runner(loss_fn, batch, parts)
            assert got == pytest.approx(whole, rel=1e-6)
            for g, w in zip((p.grad for p in model.parameters()), want, strict=True):
                torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-7)
        assert [len(b["x"]) for b, _ in split_batch(batch, 3)] == [4, 3, 3]
    finally:
        runner.close()


_SPIN = "import time\nt = time.perf_counter()\nwhile time.perf_counter() - t < 1.5: pass\n" \
        "print(time.process_time())"


@pytest.mark.skipif(not CpuShare.available(cpu_count()),
                    reason="/proc/stat does not count this process's cores (not Linux, or a "
                           "container on a bigger host): the tuner times probe steps instead")
def test_cpu_share_counts_a_real_neighbour_and_not_this_process():
    share = CpuShare()
    neighbour = subprocess.Popen([sys.executable, "-c", _SPIN], stdout=subprocess.PIPE,
                                 text=True)
    own0, t0 = time.process_time(), time.perf_counter()
    while neighbour.poll() is None:  # spin here too: this process's time must not count
        pass
    others = share.others()
    wall, own = time.perf_counter() - t0, time.process_time() - own0
    neighbour_cores = float(neighbour.stdout.read()) / wall
    # other load on the machine may only add to what the neighbour used, and the total can
    # not exceed the cores left after this process's own share
    assert neighbour_cores - 0.1 <= others <= cpu_count() - own / wall + 0.1
    assert neighbour_cores > 0.3  # it really ran beside this process


@pytest.mark.skipif(cpu_count() < 2 or not CpuShare.available(cpu_count()),
                    reason="needs /proc/stat for this process's cores and 2 or more of them")
def test_tuner_gives_up_a_core_to_a_real_neighbour():
    before = torch.get_num_threads()
    neighbour = subprocess.Popen([sys.executable, "-c", _SPIN])
    try:
        tuner = AdaptiveThreads(window_s=1.0)
        time.sleep(1.1)  # the neighbour holds a core for the whole window
        tuner.after_step(1, 0.3)
        assert (tuner.current, tuner.parts) == (1, min(cpu_count(), 8))
    finally:
        neighbour.wait()
        torch.set_num_threads(before)

"""When the eval loop launches a policy forward (harness.forwards.Forwards.should_launch).

A fake policy whose forwards block until released, so the test decides what is in flight.
"""

from __future__ import annotations

import threading

from so101_sim.harness.forwards import Forwards


class _Gate:
    """predict_chunks blocks until `release` is set; one action chunk per request."""

    concurrent_forwards = True

    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls: list[int] = []

    def predict_chunks(self, requests: list) -> list:
        self.calls.append(len(requests))
        assert self.release.wait(30), "the test never released the forward"
        return [[[0.0] * 6] * 8 for _ in requests]


def test_full_batches_launch_and_short_ones_wait_for_stepping_envs():
    f = Forwards(_Gate(), concurrent=True)
    try:
        assert not f.should_launch(0, 8, envs_stepping=False)  # nothing to forward
        assert f.should_launch(8, 8, envs_stepping=True)  # full
        assert not f.should_launch(3, 8, envs_stepping=True)  # rows may still join it
        assert f.should_launch(3, 8, envs_stepping=False)  # none can join it
    finally:
        f.policy.release.set()
        f.close()


def test_a_short_batch_takes_the_free_forward_thread():
    """One forward in flight and no env stepping: the waiting rows cannot grow until that
    forward ends, so they go out at once on the second thread; with both busy, nothing."""
    gate = _Gate()
    f = Forwards(gate, concurrent=True)
    try:
        f.launch(list(range(8)), list(range(8)))
        assert f.should_launch(3, 8, envs_stepping=False)
        assert not f.should_launch(3, 8, envs_stepping=True)
        f.launch(list(range(3)), list(range(3)))
        assert not f.should_launch(8, 8, envs_stepping=False)  # both threads busy
        gate.release.set()
        while f.inflight:
            f.wait()
            f.finished()
        assert sorted(gate.calls) == [3, 8]
    finally:
        gate.release.set()
        f.close()


def test_one_forward_at_a_time_without_a_second_thread():
    gate = _Gate()
    gate.release.set()
    f = Forwards(gate, concurrent=False)
    f.launch([0, 1], [0, 1])  # runs to the end inside launch
    assert f.should_launch(2, 8, envs_stepping=False) is False  # its result is not taken yet
    assert [len(r) for r, *_ in f.finished()] == [2]
    assert f.should_launch(2, 8, envs_stepping=False)
    f.close()


def test_a_second_forward_needs_more_envs_than_one_forward_holds():
    assert not Forwards.pair_helps(8, 8)
    assert Forwards.pair_helps(9, 8)
    assert Forwards.pair_helps(3, 2)


def test_only_a_forward_alone_may_take_a_second_core(monkeypatch):
    """No env stepping and nothing else in flight, on a machine with a core per forward
    thread to spare: the policy sees ``spare_core()`` inside that forward only."""
    import so101_sim.harness.forwards as forwards_module
    from so101_sim.harness.policies.protocol import spare_core

    class _Spare(_Gate):
        def predict_chunks(self, requests: list) -> list:
            self.seen.append((len(requests), spare_core()))
            return super().predict_chunks(requests)

    monkeypatch.setattr(forwards_module, "_threads", lambda: 1)
    for cores, concurrent in ((2, True), (2, False), (1, True)):
        monkeypatch.setattr(forwards_module, "cpu_count", lambda c=cores: c)
        gate = _Spare()
        gate.seen = []
        if not concurrent:  # its forwards run inside launch
            gate.release.set()
        f = Forwards(gate, concurrent=concurrent)
        try:
            f.launch([0] * 8, [0] * 8, alone=True)  # all envs wait for it, nothing in flight
            if concurrent:
                f.launch([0] * 3, [0] * 3, alone=True)  # the first is still in flight
                gate.release.set()
            while f.inflight:
                f.wait()
                f.finished()
            f.launch([0] * 2, [0] * 2, alone=False)  # envs are stepping beside it
            while f.inflight:
                f.wait()
                f.finished()
        finally:
            gate.release.set()
            f.close()
        want = [(8, cores >= 2), (2, False)] if not concurrent else [
            (8, cores >= 2), (3, False), (2, False)]
        assert sorted(gate.seen) == sorted(want), (cores, concurrent, gate.seen)
        assert not spare_core()  # the flag stays with the forward's thread and ends with it

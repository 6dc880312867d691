"""The harness evaluates lerobot policies beyond Diffusion: ACT chunk-wise, ACT with temporal
ensembling (a forward every step, one ensembler per env), and a policy that reads ``task``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_act import make_tiny_act_checkpoint
from tiny_policy import short_task

from so101_sim.harness import ChunkRequest, evaluate
from so101_sim.harness.policies.lerobot import LeRobotPolicy
from so101_sim.tasks import load_task

SIZE = (48, 64)


def _obs(rng: np.random.Generator) -> dict:
    return {"agent_pos": rng.uniform(-50, 50, 6).astype(np.float32),
            "pixels": {c: rng.integers(0, 255, (*SIZE, 3), dtype=np.uint8)
                       for c in ("front", "side")}}


@pytest.mark.parametrize("ensemble", [None, 0.01])
def test_act_runs_closed_loop_and_does_not_depend_on_batching(tmp_path, ensemble):
    ckpt = make_tiny_act_checkpoint(tmp_path / "act", SIZE, temporal_ensemble_coeff=ensemble)
    task = short_task(tmp_path, max_steps=12)
    runs = {}
    for n_envs in (1, 2):
        policy = LeRobotPolicy(ckpt, batch_size=2, log=lambda _: None)
        assert policy.info.n_action_steps == (1 if ensemble else 8)
        runs[n_envs] = evaluate(policy, task=task, episodes=2, n_envs=n_envs, videos=0,
                                image_size=SIZE, out_dir=tmp_path / f"e{n_envs}",
                                progress=False, report=False, log=lambda _: None)
    shas = {k: [e["actions_sha"] for e in r["per_episode"]] for k, r in runs.items()}
    assert shas[1] == shas[2] and len(shas[1]) == 2
    assert all(e["steps"] == 12 for e in runs[2]["per_episode"])


def test_temporal_ensembling_matches_lerobots_own_select_action(tmp_path):
    """Per slot, the harness's actions equal ACTPolicy.select_action on the same frames, with
    another env's requests interleaved in the batches."""
    ckpt = make_tiny_act_checkpoint(tmp_path / "act", SIZE, temporal_ensemble_coeff=0.01)
    ours = LeRobotPolicy(ckpt, batch_size=2, log=lambda _: None)
    theirs = LeRobotPolicy(ckpt, batch_size=1, log=lambda _: None)
    theirs.policy.reset()
    ours.start_episode(0, 100_000)
    ours.start_episode(1, 100_001)
    rng = np.random.default_rng(0)
    for _ in range(12):
        a, b = _obs(rng), _obs(rng)
        got = ours.predict_chunks([ChunkRequest(0, 100_000, [a]), ChunkRequest(1, 100_001, [b])])
        batch = theirs._observation_batch([ChunkRequest(0, 100_000, [a])])
        with torch.no_grad():
            want = theirs.post(theirs.policy.select_action(batch)).numpy()
        np.testing.assert_allclose(got[0, 0], want[0], rtol=1e-5, atol=1e-4)


def test_two_forwards_at_once_each_get_their_own_actions(tmp_path):
    """harness.forwards runs two predict_chunks at once on threads. lerobot's processor steps
    keep the transition in flight in an attribute, so unguarded they swapped observations
    between the threads (51 of 2000 forwards, here); each thread must get exactly the actions
    of its own observation, as one forward at a time gives."""
    import sys
    from concurrent.futures import ThreadPoolExecutor

    ckpt = make_tiny_act_checkpoint(tmp_path / "act", SIZE)
    policy = LeRobotPolicy(ckpt, batch_size=1, log=lambda _: None)
    rng = np.random.default_rng(2)
    frames = [_obs(rng) for _ in range(4)]
    for slot in range(4):
        policy.start_episode(slot, 100_000 + slot)

    def forward(slot: int) -> np.ndarray:
        return policy.predict_chunks([ChunkRequest(slot, 100_000 + slot, [frames[slot]])])

    alone = [forward(slot) for slot in range(4)]
    assert not np.array_equal(alone[0], alone[1])  # a swap would show
    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)  # switch threads often, as a busy machine does
    try:
        with ThreadPoolExecutor(2, initializer=torch.set_num_threads,
                                initargs=(torch.get_num_threads(),)) as pool:
            for i in range(150):
                pair = (2 * i) % 4, (2 * i + 1) % 4
                futures = [pool.submit(forward, slot) for slot in pair]
                for slot, fut in zip(pair, futures, strict=True):
                    np.testing.assert_array_equal(fut.result(), alone[slot])
    finally:
        sys.setswitchinterval(before)


@pytest.mark.parametrize("later_steps_see_the_row", [False, True])
def test_ensembling_checks_the_whole_chunk_for_batch_independence(tmp_path, monkeypatch,
                                                                   later_steps_see_the_row):
    """Ensembling averages every action of each chunk, so the load-time batching check must
    compare whole chunks: rows that differ only after the first action still force one
    forward per env."""
    from lerobot.policies.act.modeling_act import ACTPolicy

    def chunk(self, batch):  # position-independent first action; later ones maybe not
        rows = batch["observation.state"].shape[0]
        out = torch.zeros(rows, self.config.chunk_size, 6)
        if later_steps_see_the_row:
            out[:, 1:] += torch.arange(rows, dtype=out.dtype)[:, None, None] * 1e-3
        return out

    monkeypatch.setattr(ACTPolicy, "predict_action_chunk", chunk)
    ckpt = make_tiny_act_checkpoint(tmp_path / "act", SIZE, temporal_ensemble_coeff=0.01)
    messages: list[str] = []
    policy = LeRobotPolicy(ckpt, batch_size=2, log=messages.append)
    assert policy.batch_size == (1 if later_steps_see_the_row else 2)
    assert any("depend on its position" in m for m in messages) == later_steps_see_the_row


def _actions(policy: LeRobotPolicy, steps: int) -> np.ndarray:
    """Each forward's executed actions for two envs fed the same random frames."""
    policy.start_episode(0, 100_000)
    policy.start_episode(1, 100_001)
    rng = np.random.default_rng(1)
    out = []
    for _ in range(steps):
        a, b = _obs(rng), _obs(rng)
        out.append(policy.predict_chunks([ChunkRequest(0, 100_000, [a]),
                                          ChunkRequest(1, 100_001, [b])]))
    return np.stack(out)


def test_temporal_ensemble_flag_switches_a_checkpoint_either_way(tmp_path):
    """`--temporal-ensemble 0.01` on a chunk-wise checkpoint acts exactly like the same weights
    saved with ensembling, and `off` turns an ensembling checkpoint back into chunks."""
    chunked = make_tiny_act_checkpoint(tmp_path / "chunked", SIZE, seed=3)
    ensembled = make_tiny_act_checkpoint(tmp_path / "te", SIZE, temporal_ensemble_coeff=0.01,
                                         seed=3)
    messages: list[str] = []
    switched_on = LeRobotPolicy(chunked, temporal_ensemble_coeff=0.01, batch_size=2,
                                log=messages.append)
    assert switched_on.info.n_action_steps == 1
    assert any("temporal_ensemble_coeff=None; using 0.01 as asked" in m for m in messages)
    native = LeRobotPolicy(ensembled, batch_size=2, log=lambda _: None)
    on = _actions(switched_on, 9)  # one step past a full chunk of 8
    assert on.shape == (9, 2, 1, 6)
    np.testing.assert_array_equal(on, _actions(native, 9))

    switched_off = LeRobotPolicy(ensembled, temporal_ensemble_coeff="off", n_action_steps=8,
                                 batch_size=2, log=lambda _: None)
    assert switched_off.info.n_action_steps == 8 and switched_off.ensemble is None
    off = _actions(switched_off, 3)
    plain = LeRobotPolicy(chunked, batch_size=2, log=lambda _: None)
    np.testing.assert_array_equal(off, _actions(plain, 3))
    assert not np.array_equal(off[:, :, 0], on[:3, :, 0])  # ensembling did change the actions
    # runs with and without the flag are told apart (compare and --resume read the fingerprint)
    assert switched_on.info.fingerprint != plain.info.fingerprint
    assert switched_off.info.fingerprint not in (plain.info.fingerprint, native.info.fingerprint)
    # asking for the checkpoint's own setting is the same evaluation, so the same fingerprint
    # (an `eval --temporal-ensemble off` folder and a `curve` of the same weights pair up)
    same_as_plain = LeRobotPolicy(chunked, temporal_ensemble_coeff="off", n_action_steps=8,
                                  batch_size=2, log=lambda _: None)
    assert same_as_plain.info.fingerprint == plain.info.fingerprint
    same_as_native = LeRobotPolicy(ensembled, temporal_ensemble_coeff=0.01, batch_size=2,
                                   log=lambda _: None)
    assert same_as_native.info.fingerprint == native.info.fingerprint


def test_temporal_ensemble_flag_refuses_what_cannot_run(tmp_path):
    ensembled = make_tiny_act_checkpoint(tmp_path / "te", SIZE, temporal_ensemble_coeff=0.01)
    with pytest.raises(ValueError, match="drop --n-action-steps"):
        LeRobotPolicy(ensembled, temporal_ensemble_coeff=0.02, n_action_steps=8)
    with pytest.raises(ValueError, match="add --temporal-ensemble off"):
        LeRobotPolicy(ensembled, n_action_steps=8)
    with pytest.raises(ValueError, match="expected a finite coefficient"):
        LeRobotPolicy(ensembled, temporal_ensemble_coeff=float("nan"))


def test_curve_with_temporal_ensembling_is_a_curve_of_its_own(tmp_path):
    """`so101-sim curve --temporal-ensemble`: its rows and evaluations sit beside the
    checkpoint's own curve, each skipped when already measured."""
    from so101_sim.harness.curve import evaluate_curve, read_curve

    run = tmp_path / "run"
    make_tiny_act_checkpoint(run / "checkpoints" / "step_0000002" / "pretrained_model", SIZE)
    task = str(short_task(tmp_path, max_steps=12))
    kw = {"episodes": 1, "n_envs": 1, "progress": False, "task": task}
    te = {"temporal_ensemble_coeff": 0.01}
    own = evaluate_curve(run, **kw)
    ensembled = evaluate_curve(run, policy_options=te, **kw)
    assert [r["step"] for r in own] == [2] and "variant" not in own[0]
    assert [(r["step"], r["variant"]) for r in ensembled] == [(2, "temporal_ensemble_coeff=0.01")]
    assert read_curve(run, task) == own  # the default curve stays the checkpoint's
    assert len(read_curve(run, task, variant=None)) == 2
    assert evaluate_curve(run, policy_options=te, **kw) == ensembled  # nothing left to run
    details = {}
    stem = Path(task).stem
    for folder in (stem, f"{stem}-temporal_ensemble_coeff=0.01"):
        info = json.loads((run / "eval_curve" / folder / "step_0000002" / "eval_info.json")
                          .read_text())
        details[folder] = info["config"]["policy_details"]
    assert "temporal ensembling" not in details[stem]
    assert details[f"{stem}-temporal_ensemble_coeff=0.01"]["temporal ensembling"] == (
        "coefficient 0.01 over 8-action chunks, a forward every step")
    # The CLI draws each curve into its own plot (both measured above: nothing runs here).
    from so101_sim.cli import main

    args = ["curve", str(run), "--task", task, "--episodes", "1", "--n-envs", "1"]
    assert main(args) == 0 and main([*args, "--temporal-ensemble", "0.01"]) == 0
    assert sorted(p.name for p in run.glob("eval_curve*.png")) == [
        f"eval_curve_{stem}-temporal_ensemble_coeff=0.01.png", f"eval_curve_{stem}.png"]


def test_a_language_policy_gets_the_task_description(tmp_path):
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from tiny_task_policy.configuration_tiny_task import TinyTaskConfig
    from tiny_task_policy.modeling_tiny_task import SEEN_TASKS, TinyTaskPolicy

    cfg = TinyTaskConfig(
        input_features={"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,))},
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        device="cpu")
    out = tmp_path / "lang"
    TinyTaskPolicy(cfg).save_pretrained(out)
    pre, post = make_pre_post_processors(cfg, dataset_stats={})
    pre.save_pretrained(out)
    post.save_pretrained(out)
    SEEN_TASKS.clear()
    spec = load_task("stack")
    from so101_sim.harness import load_policy

    policy = load_policy(str(out), task=spec)
    result = evaluate(policy, task=spec, episodes=1, n_envs=1, videos=0, out_dir=tmp_path / "e",
                      progress=False, report=False, log=lambda _: None)
    assert result["aggregated"]["n_episodes"] == 1
    assert SEEN_TASKS and set(SEEN_TASKS) == {spec.description}


def test_diffusion_temporal_ensembling_averages_the_overlapping_chunks(tmp_path):
    """`--temporal-ensemble` on a Diffusion checkpoint: a forward every step, and each step's
    action is ACT's weighted mean (exp(-0.01 i), i = 0 the oldest) of what every chunk so far
    said for that step; each chunk is the horizon - To + 1 = 15 actions from the step it was
    sampled at, with the episode's own seeded noise (the same chunks one plain 15-action
    forward at a time gives), whatever env shares the batch."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_policy import make_tiny_diffusion_checkpoint

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "dp", input_size=SIZE)
    messages: list[str] = []
    ours = LeRobotPolicy(ckpt, temporal_ensemble_coeff=0.01, batch_size=2, log=messages.append)
    assert ours.info.n_action_steps == 1 and ours.ensemble.chunk_size == 15
    assert any("temporal_ensemble_coeff=None; using 0.01 as asked" in m for m in messages)
    assert "temporal ensembling" in ours.info.details
    plain = LeRobotPolicy(ckpt, n_action_steps=15, batch_size=1, log=lambda _: None)
    for p in (ours, plain):
        p.start_episode(0, 100_000)
    ours.start_episode(1, 100_001)
    rng = np.random.default_rng(0)
    chunks, got = [], []
    for _ in range(5):
        mine, other = [_obs(rng), _obs(rng)], [_obs(rng), _obs(rng)]
        got.append(ours.predict_chunks([ChunkRequest(0, 100_000, mine),
                                        ChunkRequest(1, 100_001, other)])[0, 0])
        chunks.append(plain.predict_chunks([ChunkRequest(0, 100_000, mine)])[0])
    assert chunks[0].shape == (15, 6)
    for t in range(5):
        weights = np.exp(-0.01 * np.arange(t + 1))
        want = sum(w * chunks[k][t - k] for k, w in enumerate(weights)) / weights.sum()
        np.testing.assert_allclose(got[t], want, rtol=1e-5, atol=1e-3)
    assert not np.allclose(got[1], chunks[1][0], atol=1e-3)  # step 1 is a mean, not the newest
    with pytest.raises(ValueError, match="drop --n-action-steps"):
        LeRobotPolicy(ckpt, temporal_ensemble_coeff=0.01, n_action_steps=8)

"""Files from someone else are data: crafted checkpoints and run folders never run code.
Also the trainer's resume edge cases and the --device plumbing (on CPU)."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest
import torch

from so101_sim.utils.devices import resolve_device, resolve_precision
from so101_sim.utils.trust import UntrustedCheckpointError, check_processor_files

SHIPPED = Path(__file__).parents[1] / "policy" / "pick_place_diffusion"


class _Boom:
    """Pickles into a call of os.system that would create `marker`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def _crafted_checkpoint(tmp_path: Path, marker: Path) -> Path:
    ck = tmp_path / "ck"
    shutil.copytree(SHIPPED, ck)
    spec = json.loads((ck / "policy_preprocessor.json").read_text())
    spec["steps"].insert(0, {"class": "os.system", "config": {"command": f"touch {marker}"}})
    (ck / "policy_preprocessor.json").write_text(json.dumps(spec))
    return ck


def test_processor_naming_a_class_is_refused_before_loading(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    ck = _crafted_checkpoint(tmp_path, marker)
    with pytest.raises(UntrustedCheckpointError, match=r"policy_preprocessor\.json: step 0 names "
                                                       r"the Python class 'os\.system'"):
        check_processor_files(ck)
    from so101_sim.harness import load_policy

    with pytest.raises(UntrustedCheckpointError, match=r"os\.system"):
        load_policy(str(ck))
    from so101_sim.harness.export import export_policy

    (ck / "so101_sim_train.json").write_text((SHIPPED / "so101_sim_train.json").read_text())
    with pytest.raises(UntrustedCheckpointError, match=r"os\.system"):
        export_policy(ck, tmp_path / "exported")
    assert not (tmp_path / "exported").exists()
    assert not marker.exists()


def test_unknown_registry_name_and_escaping_state_file_are_refused(tmp_path: Path) -> None:
    ck = tmp_path / "ck"
    shutil.copytree(SHIPPED, ck)
    path = ck / "policy_postprocessor.json"
    good = path.read_text()
    spec = json.loads(good)
    spec["steps"][0]["registry_name"] = "not_a_step"
    path.write_text(json.dumps(spec))
    with pytest.raises(UntrustedCheckpointError, match="registry_name 'not_a_step'"):
        check_processor_files(ck)
    spec = json.loads(good)
    spec["steps"][-1]["state_file"] = "../../etc/passwd"
    path.write_text(json.dumps(spec))
    with pytest.raises(UntrustedCheckpointError, match="plain file name"):
        check_processor_files(ck)
    path.write_bytes(b"\xff\xfe not json")
    with pytest.raises(UntrustedCheckpointError, match="not valid UTF-8 JSON"):
        check_processor_files(ck)


def test_shipped_checkpoint_passes_the_check() -> None:
    check_processor_files(SHIPPED, "diffusion")


def test_crafted_training_state_is_not_unpickled(tmp_path: Path) -> None:
    from so101_sim.train.state import TrainError, load_training_state

    marker = tmp_path / "pwned"
    path = tmp_path / "training_state.pt"
    torch.save({"step": 2, "model": _Boom(marker)}, path)  # torch.save pickles it
    with pytest.raises(TrainError, match="not loaded \\(that could run code\\)"):
        load_training_state(path, "cpu")
    with path.open("wb") as f:
        pickle.dump({"model": _Boom(marker)}, f)
    with pytest.raises(TrainError, match=r"could run code|cannot be read"):
        load_training_state(path, "cpu")
    assert not marker.exists()


def test_resume_without_a_checkpoint_is_refused(tmp_path: Path) -> None:
    from so101_sim.train.trainer import TrainError, train

    with pytest.raises(TrainError, match="does not exist, so there is nothing to continue"):
        train(tmp_path / "ds", tmp_path / "typo", steps=1, resume=True, progress=False)
    (tmp_path / "half").mkdir()
    with pytest.raises(TrainError, match="holds no checkpoint"):
        train(tmp_path / "ds", tmp_path / "half", steps=1, resume=True, progress=False)


def test_torn_log_line_is_dropped(tmp_path: Path) -> None:
    from so101_sim.train.state import truncate_log

    log = tmp_path / "train_log.jsonl"
    log.write_text('{"step": 1, "loss": 1.0}\n{"step": 2, "loss": 0.9}\n{"step": 3, "lo')
    truncate_log(log, 2)
    assert log.read_text() == '{"step": 1, "loss": 1.0}\n{"step": 2, "loss": 0.9}\n'


def test_device_resolution_on_this_machine() -> None:
    assert resolve_device("cpu") == "cpu"
    auto = resolve_device("auto")
    assert auto in ("cpu", "cuda", "mps")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="--device cuda: torch sees no CUDA GPU"):
            resolve_device("cuda")
        assert auto != "cuda"
    with pytest.raises(ValueError, match="device='tpu' is invalid"):
        resolve_device("tpu")
    assert resolve_precision("fp32", "cpu") == "fp32"
    assert resolve_precision("auto", "mps") == "fp32"
    assert resolve_precision("auto", "cuda") == "fp32"  # bf16 was slower on an H200
    assert resolve_precision("auto", "cpu") in ("fp32", "bf16")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine: the "
                    "CUDA path of --device is only exercised where one exists")
def test_cuda_chunks_match_cpu_and_an_eval_runs(tmp_path: Path) -> None:
    """--device cuda: the weights sit on the GPU, the episode seeds' noise (drawn on the CPU)
    gives the CPU's chunks up to float rounding, and a closed-loop eval runs end to end."""
    import sys

    import numpy as np

    from so101_sim.harness import ChunkRequest, evaluate
    from so101_sim.harness.policies.lerobot import LeRobotPolicy

    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_policy import make_tiny_diffusion_checkpoint, short_task

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "tiny", input_size=(48, 64),
                                          dataset_image_size=(96, 128))
    rng = np.random.default_rng(0)
    reqs = [ChunkRequest(i, 100000 + i, [{
        "agent_pos": rng.uniform(-50, 50, 6).astype(np.float32),
        "pixels": {c: rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
                   for c in ("front", "side")}} for _ in range(2)]) for i in range(3)]
    chunks, policies = {}, {}
    for device in ("cpu", "cuda"):
        policy = policies[device] = LeRobotPolicy(ckpt, device=device, log=lambda _: None)
        assert policy.cfg.device == device
        assert {p.device.type for p in policy.policy.parameters()} == {device}
        for r in reqs:
            policy.start_episode(r.slot, r.seed)
        chunks[device] = policy.predict_chunks(reqs)
    assert chunks["cuda"].dtype == np.float32 and chunks["cuda"].shape == chunks["cpu"].shape
    # TF32 convolutions on the GPU round differently from the CPU's fp32: close, not equal
    diff = float(np.abs(chunks["cuda"] - chunks["cpu"]).max())
    print(f"max |cuda - cpu| over the chunks: {diff:.2e} (scale {np.abs(chunks['cpu']).max():.1f})")
    assert diff < 0.01 * float(np.abs(chunks["cpu"]).max())
    result = evaluate(policies["cuda"], task=str(short_task(tmp_path, max_steps=16)),
                      episodes=2, n_envs=2, videos=0, report=False, out_dir=tmp_path / "eval",
                      progress=False, log=lambda _: None)
    assert [e["steps"] for e in result["per_episode"]] == [16, 16]

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
    assert resolve_precision("auto", "cpu") in ("fp32", "bf16")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine: the "
                    "CUDA path of --device is only exercised where one exists")
def test_cuda_eval_matches_shape() -> None:
    from so101_sim.harness import load_policy

    policy = load_policy(str(SHIPPED), device="cuda")
    assert policy.cfg.device == "cuda"

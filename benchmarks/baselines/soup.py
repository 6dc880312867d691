"""Average the weights of checkpoints fine-tuned from one another (a "model soup") into one.

    .venv/bin/python benchmarks/baselines/soup.py CKPT_A CKPT_B [CKPT_C ...] --out DIR

The checkpoints must be one architecture with one normalisation: the same ``config.json`` and
byte-identical processor state files (the same dataset's statistics); otherwise it refuses,
naming the file that differs. Every floating-point tensor of ``model.safetensors`` becomes the
plain mean; any other tensor must be equal in all of them. DIR gets the first checkpoint's
config and processors, the mean weights, and its ``so101_sim_train.json`` with a ``soup`` entry
(each ingredient's path and weights sha256). Only tensors and JSON are read: no code.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
from pathlib import Path

import torch
from safetensors.torch import load, save_file

SIDE = "so101_sim_train.json"


def check_same(paths: list[Path]) -> None:
    """Refuse ingredients whose config or processor files differ from the first's."""
    first = paths[0]
    names = sorted(p.name for p in first.iterdir() if p.name.startswith("policy_"))
    for other in paths[1:]:
        if json.loads((other / "config.json").read_text()) != json.loads(
                (first / "config.json").read_text()):
            sys.exit(f"soup: {other}/config.json differs from {first}/config.json; only one "
                     "architecture with one setting can be averaged")
        for name in names:
            if (other / name).read_bytes() != (first / name).read_bytes():
                sys.exit(f"soup: {other / name} differs from {first / name} (another dataset's "
                         "normalisation); average checkpoints trained on the same demos")


def soup(paths: list[Path]) -> tuple[dict[str, torch.Tensor], list[dict[str, str]]]:
    """The mean of the ingredients' weights, and what each ingredient was."""
    parts, made_of = [], []
    for path in paths:
        raw = (path / "model.safetensors").read_bytes()
        parts.append(load(raw))
        made_of.append({"path": str(path.resolve()),
                        "model_sha256": hashlib.sha256(raw).hexdigest()[:16]})
    mean = {}
    for key, first in parts[0].items():
        if any(key not in p or p[key].shape != first.shape for p in parts[1:]):
            sys.exit(f"soup: tensor {key} is missing or has another shape in some ingredient")
        if first.is_floating_point():
            mean[key] = (torch.stack([p[key].double() for p in parts]).mean(0)
                         .to(first.dtype).contiguous())
        elif all(torch.equal(p[key], first) for p in parts[1:]):
            mean[key] = first
        else:
            sys.exit(f"soup: non-float tensor {key} differs between ingredients")
    return mean, made_of


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="pretrained_model folders")
    parser.add_argument("--out", type=Path, required=True, help="new checkpoint folder")
    args = parser.parse_args()
    paths = [p.expanduser() for p in args.checkpoints]
    if len(paths) < 2:
        parser.error("give at least two checkpoints")
    for p in paths:
        if not (p / "model.safetensors").is_file() or not (p / "config.json").is_file():
            parser.error(f"{p} is not a checkpoint folder (model.safetensors and config.json)")
    if args.out.exists():
        parser.error(f"--out {args.out} exists; give a new folder")
    check_same(paths)
    mean, made_of = soup(paths)
    tmp = args.out.with_name(args.out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for f in paths[0].iterdir():
        if f.name not in ("model.safetensors", SIDE) and f.is_file():
            shutil.copy2(f, tmp / f.name)
    save_file(mean, str(tmp / "model.safetensors"), metadata={"format": "pt"})
    side = json.loads((paths[0] / SIDE).read_text()) if (paths[0] / SIDE).is_file() else {}
    side.update({"weights": f"mean of {len(paths)} checkpoints' weights", "soup": made_of})
    (tmp / SIDE).write_text(json.dumps(side, indent=2))
    tmp.rename(args.out)
    print(f"soup: the mean of {len(paths)} checkpoints -> {args.out}")


if __name__ == "__main__":
    main()

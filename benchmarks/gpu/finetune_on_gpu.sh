#!/usr/bin/env bash
# Train on a lent GPU in one short call, by default fine-tuning the shipped suite weights:
#   bash benchmarks/gpu/finetune_on_gpu.sh DATASET OUT TRAIN_S NAME:PRESET:BATCH:STEPS[:DATA[:INIT]] ...
# Each NAME runs `so101-sim train --init-from INIT` (default policy/suite_diffusion; a path
# relative to the repo or absolute; `scratch` trains from random weights) with its preset, batch
# and steps, on its own dataset DATA when given (else DATASET), all at once on the one GPU (a step
# of these presets is launch-bound, so the runs share it), stopped by SIGTERM after TRAIN_S
# seconds if not done (the trainer checkpoints on SIGTERM).
# Each run's last policy comes back as NAME.tar (weights in fp16, as `so101-sim export` ships
# them), split into 15 MB parts to pass the 16 MiB-per-file limit: `cat NAME.tar.* | tar x`.
# DATASET is made small enough to travel by benchmarks/gpu/pack_dataset.py; where PyAV is
# missing the frame cache decodes with OpenCV (benchmarks/gpu/train_without_pyav.py).
# Wheels of the missing dependencies are installed from .whl/ when it exists and lerobot
# does not import (see
# benchmarks/README.md, "gpu_check.sh"). DEVICE=cpu makes it a dry run without a GPU.
set -uo pipefail
data=${1:?usage: finetune_on_gpu.sh DATASET OUT TRAIN_S NAME:PRESET:BATCH:STEPS ...}
out=${2:?}
train_s=${3:?}
shift 3
py=${PY:-python3}
dev=${DEVICE:-cuda}
runs=${RUNS:-/tmp/ft_runs}
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
mkdir -p "$out" "$runs"
t0=$SECONDS
if [ -d "$repo/.whl" ] && ! "$py" -c 'import lerobot, diffusers' 2> /dev/null; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$repo"/.whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$repo${PYTHONPATH:+:$PYTHONPATH}
else
  export PYTHONPATH=$repo${PYTHONPATH:+:$PYTHONPATH}
fi
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
echo "setup: $((SECONDS - t0)) s"
[ "$dev" = cuda ] && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
"$py" -c 'import torch, lerobot, diffusers; print("torch", torch.__version__, "cuda",
torch.cuda.is_available(), "lerobot", lerobot.__version__, "diffusers", diffusers.__version__)'

# what comes back from a call is capped in total: two 28.6 MB policies fit, a third was left out
[ $# -le 2 ] || echo "note: $# policies will be packed; a call returns about two, so fetch the" \
  "rest in a next call on the warm machine (split -b 15000000 -d $runs/NAME.tar \$OUT/NAME.tar.)"
names=()
for spec in "$@"; do
  IFS=: read -r name preset batch steps own init <<< "$spec"
  names+=("$name")
  init=${init:-policy/suite_diffusion}
  case $init in scratch) from=() ;; /*) from=(--init-from "$init") ;;
    *) from=(--init-from "$repo/$init") ;; esac
  echo "=== $name: preset $preset, batch $batch, $steps steps, ${own:-$data}, from $init," \
    "at most $train_s s"
  timeout -s TERM "$train_s" "$py" "$here/train_without_pyav.py" --preset "$preset" \
    --dataset "${own:-$data}" --out "$runs/$name" "${from[@]}" \
    --batch-size "$batch" --steps "$steps" --device "$dev" > "$out/$name.log" 2>&1 &
done
wait
echo "training: $((SECONDS - t0)) s"

for name in "${names[@]}"; do
  run=$runs/$name
  last=$(ls -d "$run"/checkpoints/step_* 2>/dev/null | tail -n 1)
  [ -d "$run/pretrained_model" ] && last=$run
  tail -n 3 "$out/$name.log" | tr '\r' '\n' | tail -n 3
  if [ -z "$last" ]; then echo "=== $name: no checkpoint"; continue; fi
  tail -n 1 "$run/train_log.jsonl"
  pack=$runs/pack_$name
  rm -rf "$pack" && mkdir -p "$pack"
  cp "$last"/pretrained_model/* "$pack"/  # the run's final policy, or its last checkpoint's
  cp "$run/train_log.jsonl" "$pack"/
  "$py" -c 'import sys, torch
from safetensors.torch import load_file, save_file
p = sys.argv[1] + "/model.safetensors"
save_file({k: v.half() if v.is_floating_point() else v for k, v in load_file(p).items()}, p)' "$pack"
  tar cf "$runs/$name.tar" -C "$pack" .
  split -b 15000000 -d "$runs/$name.tar" "$out/$name.tar."
  echo "=== $name: $(basename "$last") packed, $(du -b "$runs/$name.tar" | cut -f1) bytes"
done
echo "total: $((SECONDS - t0)) s"

#!/usr/bin/env bash
# The checks that need a CUDA GPU, in one short run (a lent GPU's minutes are few):
#   bash benchmarks/gpu_check.sh DATASET OUT
# 1. the CUDA tests (tests/test_trust.py -k cuda: chunks on the GPU against the CPU, an eval);
# 2. per-step training speed of the seed, cpu and act presets on the GPU (synthetic batches of
#    the trainer's shapes, fp32 and bf16);
# 3. `so101-sim train --preset seed --device cuda` on DATASET for TRAIN_STEPS steps (the real
#    loader, EMA and checkpointing);
# 4. that checkpoint evaluated with its forwards on the GPU and on the CPU, one env worker per
#    core, paired with `so101-sim compare`;
# 5. the shipped policy likewise on 200 seeds, where policy/pick_place_diffusion is present;
# 6. recording speed with one worker per core.
# Each step has its own time limit and prints its wall time; a failing step does not stop the
# others. Needs the project importable (`make venv`, or PYTHONPATH) and `so101-sim` on PATH.
# DEVICE=cpu makes it a dry run on a machine without a GPU.
set -uo pipefail
data=${1:?usage: gpu_check.sh DATASET OUT}
out=${2:?usage: gpu_check.sh DATASET OUT}
py=${PY:-python3}
sim=${SIM:-so101-sim}
dev=${DEVICE:-cuda}
train_steps=${TRAIN_STEPS:-400}
episodes=${EVAL_EPISODES:-32}
cores=$(nproc)
mkdir -p "$out"
export HF_HUB_OFFLINE=1 MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1

step() {  # step LIMIT_S LABEL CMD...: run one check, print its wall time and exit code
  local limit=$1 label=$2; shift 2
  echo "=== $label"
  local t0=$SECONDS
  timeout "$limit" "$@"
  echo "=== $label: rc=$? in $((SECONDS - t0)) s"
}

evals() {  # evals POLICY EPISODES NAME: the policy with its forwards on $dev, then on the CPU
  local d
  for d in "$dev" cpu; do
    step 240 "$3, $2 episodes, forwards on $d, $cores envs" "$sim" eval --policy "$1" \
      --device "$d" --episodes "$2" --n-envs "$cores" --videos 0 --out "$out/eval_$3_$d"
  done
  [ "$dev" != cpu ] && "$sim" compare "$out/eval_$3_$dev" "$out/eval_$3_cpu"
}

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
"$py" -c 'import torch; print("torch", torch.__version__, "cuda", torch.cuda.is_available(),
torch.cuda.get_device_name(0) if torch.cuda.is_available() else "-")'
echo "cores $cores"

step 150 "CUDA tests" "$py" -m pytest -q -s -p no:cacheprovider tests/test_trust.py -k cuda
step 200 "train step speed (synthetic batches)" "$py" benchmarks/bench_train_step.py \
  --device "$dev" --preset seed,cpu,act --variants fp32,bf16 --steps "${BENCH_STEPS:-30}" \
  --warmup 5
step 240 "so101-sim train --preset seed --device $dev, $train_steps steps" "$sim" train \
  --preset seed --dataset "$data" --out "$out/seed" --device "$dev" --steps "$train_steps"
tail -n 2 "$out/seed/train_log.jsonl"
[ -d "$out/seed/pretrained_model" ] && evals "$out/seed/pretrained_model" "$episodes" seed
[ -f policy/pick_place_diffusion/model.safetensors ] \
  && evals policy/pick_place_diffusion 200 shipped
step 150 "so101-sim record, 48 episodes, $cores workers" "$sim" record --task pick_place \
  --episodes 48 --out "$out/rec48" --image-size 120x160 --workers "$cores" --dart-noise 1.5 \
  --grasp-clearance 0.012

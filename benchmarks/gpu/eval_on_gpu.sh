#!/usr/bin/env bash
# The shipped policy's evaluation on a lent GPU machine, in one call:
#   bash benchmarks/gpu/eval_on_gpu.sh OUT        # carry [.whl, .gl]
# 1. the CUDA tests (tests/test_trust.py -k cuda);
# 2. `so101-sim eval` of policy/pick_place_diffusion on 200 seeds with its forwards on the GPU,
#    then on the machine's CPU cores, one env worker per core, paired with `so101-sim compare`;
# 3. benchmarks/bench_against.py (noise 0.0125, 3 repeats) against the GPU run of step 2.
# DEVICE (cuda) and EPISODES (200) may be set.
# The GPU image lacks the project's dependencies: benchmarks/gpu/site_setup.sh unpacks them
# from the carried .whl/ and .gl/.
# policy/suite_diffusion's weights and benchmarks/baselines/ must be moved aside for the call
# (the tree would not fit).
# SETUP=0 skips the unpacking (a dry run where the project's venv is active: DEVICE=cpu
# EPISODES=4 SETUP=0 PATH=.venv/bin:$PATH bash benchmarks/gpu/eval_on_gpu.sh /tmp/x).
set -uo pipefail
out=${1:?usage: eval_on_gpu.sh OUT}
dev=${DEVICE:-cuda}
episodes=${EPISODES:-200}
runs=$(mktemp -d)
mkdir -p "$out"
if [ "${SETUP:-1}" = 1 ]; then source benchmarks/gpu/site_setup.sh; fi
export HF_HUB_OFFLINE=1 MUJOCO_GL=egl PYTHONUNBUFFERED=1
cores=$(nproc)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null
so101-sim --version
echo "cores $cores"
python -c 'from so101_sim.sim.meshes import find_mesh_dir as f; import sys; sys.exit(f() is None)' \
  || { echo "no SO-101 meshes: the scene would draw primitives; stopping"; exit 1; }

step() {  # step LIMIT_S LABEL CMD...: one check, its wall time and exit code
  local limit=$1 label=$2; shift 2
  echo "=== $label"
  local t0=$EPOCHREALTIME
  timeout "$limit" "$@"
  local rc=$?
  echo "=== $label: rc=$rc in $(awk "BEGIN {printf \"%.1f\", $EPOCHREALTIME - $t0}") s"
}

step 150 "CUDA tests" python -m pytest -q -s -p no:cacheprovider tests/test_trust.py -k cuda
for d in "$dev" cpu; do
  step 200 "shipped policy, $episodes seeds, forwards on $d, $cores envs" so101-sim eval \
    --policy policy/pick_place_diffusion --device "$d" --episodes "$episodes" \
    --n-envs "$cores" --videos 0 --out "$runs/eval_$d"
  cp "$runs/eval_$d/eval_info.json" "$out/eval_$d.json"
  [ "$dev" = cpu ] && break
done
[ "$dev" != cpu ] && so101-sim compare "$runs/eval_$dev" "$runs/eval_cpu"
step 300 "bench_against, noise 0.0125, 3 repeats" python benchmarks/bench_against.py \
  policy/pick_place_diffusion --noise 0.0125 --repeats 3 --episodes "$episodes" \
  --reference "$runs/eval_$dev" --out "$runs/against"

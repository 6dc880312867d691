#!/usr/bin/env bash
# ACT on pick_place against the shipped Diffusion policies, on the same 200 evaluation seeds
# (README.md here, "ACT on pick_place"):
#   bash benchmarks/baselines/act_check.sh CHECKPOINT OUT_DIR    (EPISODES=8 for a quick look)
# Evaluates CHECKPOINT (an `act` preset run's checkpoint) chunk-wise (8 of each 32-step chunk,
# as trained) and with temporal ensembling (a forward every step, coefficient 0.01 as in ACT's
# paper), then compares each seed by seed with the per-seed results of policy/suite_diffusion
# (pick_place) and policy/pick_place_diffusion.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
sim=${SIM:-$repo/.venv/bin/so101-sim}
ckpt=${1:?usage: act_check.sh CHECKPOINT OUT_DIR}
out=${2:?usage: act_check.sh CHECKPOINT OUT_DIR}
mkdir -p "$out/shipped/suite_diffusion" "$out/shipped/pick_place_diffusion"
cp "$repo/policy/suite_diffusion/eval_info_pick_place.json" "$out/shipped/suite_diffusion/eval_info.json"
cp "$repo/policy/pick_place_diffusion/eval_info.json" "$out/shipped/pick_place_diffusion/eval_info.json"
for mode in chunked ensembled; do
  extra=()
  [ "$mode" = ensembled ] && extra=(--temporal-ensemble 0.01)
  [ -f "$out/eval/$mode/eval_info.json" ] ||
    "$sim" eval --policy "$ckpt" --task pick_place --episodes "${EPISODES:-200}" --n-envs 16 --videos 4 \
      --out "$out/eval/$mode" "${extra[@]}"
  [ "${EPISODES:-200}" = 200 ] || continue  # the shipped runs have all 200 seeds
  for ref in suite_diffusion pick_place_diffusion; do
    "$sim" compare "$out/eval/$mode" "$out/shipped/$ref" --out "$out/compare/$mode-vs-$ref"
  done
done
"$sim" compare "$out/eval/ensembled" "$out/eval/chunked" --out "$out/compare/ensembled-vs-chunked"

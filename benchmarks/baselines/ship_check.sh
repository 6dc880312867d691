#!/usr/bin/env bash
# Is a suite checkpoint better than the shipped policy/suite_diffusion? (README.md here, "Recipe")
#   bash benchmarks/baselines/ship_check.sh CHECKPOINT OUT_DIR
# Exports CHECKPOINT as the shipped copy would be (fp16), evaluates that copy on the six tasks'
# 200 evaluation seeds (from 100000, as the shipped card's), compares it seed by seed with the
# shipped card's per-seed results, then writes the card with the new numbers. Nothing under
# policy/ is touched: copying OUT_DIR/suite_diffusion there is the shipping decision.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
sim=${SIM:-$repo/.venv/bin/so101-sim}
ckpt=${1:?usage: ship_check.sh CHECKPOINT OUT_DIR}
out=${2:?usage: ship_check.sh CHECKPOINT OUT_DIR}
tasks=${TASKS:-pick_place lift stack tidy pick_place_anywhere pick_place_dr}
shipped=$repo/policy/suite_diffusion
mkdir -p "$out"
"$sim" export "$ckpt" --out "$out/suite_diffusion"
evals=()
for t in $tasks; do
  [ -f "$out/eval/$t/eval_info.json" ] ||
    "$sim" eval --policy "$out/suite_diffusion" --task "$t" --episodes 200 --n-envs 16 \
      --videos 2 --out "$out/eval/$t"
  evals+=(--eval "$out/eval/$t")
  mkdir -p "$out/shipped/$t"
  cp "$shipped/eval_info_$t.json" "$out/shipped/$t/eval_info.json"
  "$sim" compare "$out/eval/$t" "$out/shipped/$t" --out "$out/compare/$t"
done
"$sim" export "$ckpt" --out "$out/suite_diffusion" "${evals[@]}"
"$repo/.venv/bin/python" "$here/ship_table.py" "$out"

#!/usr/bin/env bash
# Does image augmentation lift pick_place_dr? (README.md here, "What pick_place_dr's failures
# come from"), resumable:
#   bash benchmarks/baselines/train_ft_aug.sh RUNS_DIR [PRESET] [--resume | --stop-at N ...]
# Fine-tunes the shipped policy/suite_diffusion with PRESET (default cpu_ft_aug; cpu_ft is the
# control without augmentation) on RUNS_DIR/data/suite_dart_120 into RUNS_DIR/runs/ft_PRESET,
# on a 10000-step cosine (pause early with --stop-at). Like train_act_suite.sh it runs a
# snapshot of the code (RUNS_DIR/code_PRESET) at idle priority. A run folder without frames
# borrows the act_suite run's decoded frames (same dataset, same 60x80 size) by hard link.
# Evaluate a checkpoint with ship_check.sh (TASKS="pick_place_dr pick_place" for the quick look).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
runs=${1:?usage: train_ft_aug.sh RUNS_DIR [PRESET] [--resume | --stop-at N]}
shift
preset=cpu_ft_aug
if [ $# -gt 0 ] && [ "${1#--}" = "$1" ]; then preset=$1; shift; fi
runs=$(cd "$runs" && pwd)
code=$runs/code_$preset
out=$runs/runs/ft_$preset
if [ ! -d "$code/so101_sim" ]; then
  mkdir -p "$code"
  git -C "$repo" archive HEAD so101_sim assets envs policy | tar x -C "$code"
  git -C "$repo" rev-parse HEAD > "$code/COMMIT"
fi
if [ ! -d "$out/frame_cache" ] && [ -d "$runs/runs/act_suite/frame_cache" ]; then
  mkdir -p "$out/frame_cache"
  ln "$runs/runs/act_suite/frame_cache"/*_60x80_*.npy "$out/frame_cache/"
fi
init=(--init-from "$code/policy/suite_diffusion")
for a in "$@"; do [ "$a" = --resume ] && init=(); done
export PYTHONPATH=$code HF_HUB_OFFLINE=1
exec chrt -i 0 "$repo/.venv/bin/python" -m so101_sim.cli train --preset "$preset" \
  --dataset "$runs/data/suite_dart_120" --out "$out" --steps 10000 "${init[@]}" "$@"

#!/usr/bin/env bash
# The ACT six-task run (README.md here, "ACT on the six tasks"), resumable:
#   bash benchmarks/baselines/train_act_suite.sh RUNS_DIR [--resume]
# Trains the `act` preset on RUNS_DIR/data/suite_dart_120 (record_suite.sh RUNS_DIR/data) into
# RUNS_DIR/runs/act_suite, 60000 steps, a checkpoint every 500. It runs the code of a snapshot
# (RUNS_DIR/code, `git archive` of HEAD made on the first start) so edits to the repo do not
# change a run in flight, at idle priority (SCHED_IDLE) so foreground work goes first.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
runs=${1:?usage: train_act_suite.sh RUNS_DIR [--resume]}
shift
runs=$(cd "$runs" && pwd)
if [ ! -d "$runs/code/so101_sim" ]; then
  mkdir -p "$runs/code"
  git -C "$repo" archive HEAD so101_sim assets envs policy/presets | tar x -C "$runs/code"
  git -C "$repo" rev-parse HEAD > "$runs/code/COMMIT"
fi
export PYTHONPATH=$runs/code HF_HUB_OFFLINE=1
exec chrt -i 0 "$repo/.venv/bin/python" -m so101_sim.cli train --preset act \
  --dataset "$runs/data/suite_dart_120" --out "$runs/runs/act_suite" --steps 60000 "$@"

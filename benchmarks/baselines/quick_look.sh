#!/usr/bin/env bash
# A look at one checkpoint of the ACT six-task run on the first N evaluation seeds per task,
# temporal ensembling on (README.md here, "ACT on the six tasks"):
#   bash benchmarks/baselines/quick_look.sh RUNS_DIR STEP [N] [PREFIX]
# Pause training first (kill -STOP), resume it after (kill -CONT). Each task's per-seed result
# is copied to benchmarks/baselines/<task>/<PREFIX>_te_step_<STEP>.json (PREFIX: act_suite4, the
# run started on the fourth recording; act_suite3 was the run lost at 19180, act_suite the one
# lost at 18457), and paired with the shipped policy/suite_diffusion card's outcomes on the same
# seeds (pair_with_card.py). A file already there is never overwritten: the script stops before
# evaluating.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
sim=${SIM:-$repo/.venv/bin/so101-sim}
runs=${1:?usage: quick_look.sh RUNS_DIR STEP [N] [PREFIX]}
step=${2:?usage: quick_look.sh RUNS_DIR STEP [N] [PREFIX]}
n=${3:-50}
prefix=${4:-act_suite4}
tasks="pick_place lift stack tidy pick_place_anywhere pick_place_dr"
run=$runs/runs/act_suite
name=$(printf '%s_te_step_%07d.json' "$prefix" "$step")
for t in $tasks; do
  if [ -e "$here/$t/$name" ]; then
    echo "quick_look.sh: $here/$t/$name exists; pass another PREFIX (4th argument) or move it" >&2
    exit 2
  fi
done
for t in $tasks; do
  "$sim" curve "$run" --task "$t" --steps "$step" --episodes "$n" --n-envs 32 \
    --temporal-ensemble 0.01
  src=$run/eval_curve/$t-temporal_ensemble_coeff=0.01/$(printf "step_%07d" "$step")
  cp "$src/eval_info.json" "$here/$t/$name"
done
"$repo/.venv/bin/python" "$here/pair_with_card.py" "$name"

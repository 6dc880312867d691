#!/usr/bin/env bash
# Records the suite's demonstrations and merges them (the recipe in README.md, "Recipe").
#   bash benchmarks/baselines/record_suite.sh DATA_DIR [--right]
# Resumable: a dataset that exists is continued with --resume (finished episodes are kept).
# --right also records the right-hand grasp demos (tasks/*_right.toml, 100 each, seeds from
# 50000) and merges all eight into DATA_DIR/suite_right_120; without it the six go into
# DATA_DIR/suite_dart_120.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
sim=${SIM:-$repo/.venv/bin/so101-sim}
py=${PY:-$repo/.venv/bin/python}
data=${1:?usage: record_suite.sh DATA_DIR [--right]}
mkdir -p "$data"
common=(--workers 2 --grasp-clearance 0.012 --image-size 120x160)

rec() {  # rec OUT EPISODES ARGS...
  local out=$1 n=$2; shift 2
  local resume=()
  [ -f "$out/meta/info.json" ] && resume=(--resume)
  "$sim" record --episodes "$n" --out "$out" "${common[@]}" "${resume[@]}" "$@"
}

for t in pick_place lift tidy pick_place_anywhere pick_place_dr; do
  rec "$data/${t}_dart_120" 200 --task "$t" --dart-noise 1.5
done
# stack: at noise 1.5 the expert keeps 7/60 episodes (dropped, misplaced), at 0.75 36/60
rec "$data/stack_dart_120" 200 --task stack --dart-noise 0.75
sources=()
for t in pick_place lift tidy pick_place_anywhere pick_place_dr stack; do
  sources+=("$data/${t}_dart_120")
done
merged=$data/suite_dart_120
if [ "${2:-}" = "--right" ]; then
  for t in lift_right pick_place_anywhere_right; do
    rec "$data/${t}_dart_120" 100 --task "$here/tasks/$t.toml" --dart-noise 1.5 --seed-start 50000
    sources+=("$data/${t}_dart_120")
  done
  merged=$data/suite_right_120
fi
[ -f "$merged/meta/info.json" ] || "$py" "$here/merge.py" "$merged" "${sources[@]}"

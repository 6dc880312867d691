#!/usr/bin/env bash
# The second of two calls that fine-tune on a recording too large for one call (64 MiB travels
# per call, repo included). Call 1 carries half the packed dataset and the wheels and stashes
# them outside the repo, where they outlive the call while the machine stays warm (30 s):
#   run(carry=[".gpuwork/A", ".whl"]):
#     mkdir -p /root/stash && cp -r .gpuwork/A /root/stash/A && cp -r .whl /root/stash/whl
# Call 2 carries the other half and runs this script, which joins the halves and hands over to
# finetune_on_gpu.sh (one or more SPECs, NAME:PRESET:BATCH:STEPS[:DATA[:INIT]] as there, all
# at once; fp16 policies back as NAME.tar.*), plus the policy of the first run's checkpoint
# MID_STEP (a number among the arguments) as midMID_STEP.tar.* for a second point on its curve:
#   run(carry=[".gpuwork/B"]):
#     bash benchmarks/gpu/finetune_from_stash.sh .gpuwork/B TRAIN_S SPEC [SPEC ...] [MID_STEP]
# Anything else a run needs (another dataset, an init checkpoint) can be stashed by an earlier
# call too and named by its /root/stash path in the SPEC.
# A later call on the same warm machine can go on from the last checkpoint with --resume: the
# frame cache stays in /dev/shm, the joined dataset in /root/stash/data.
set -uo pipefail
half=${1:?usage: finetune_from_stash.sh HALF_B TRAIN_S SPEC [SPEC ...] [MID_STEP]}
train_s=${2:?}
shift 2
specs=()
mid=
for arg in "$@"; do
  if [[ $arg =~ ^[0-9]+$ ]]; then mid=$arg; else specs+=("$arg"); fi
done
[ ${#specs[@]} -gt 0 ] || { echo "no NAME:PRESET:BATCH:STEPS given"; exit 2; }
t0=$SECONDS
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
stash=${STASH:-/root/stash}
data=$stash/data
if [ ! -d "$stash/A" ]; then
  echo "$stash/A is missing: call 1 ran on another machine (it was given back); run it again"
  exit 3
fi
mkdir -p "$data" && cp -r "$stash"/A/. "$data"/ && cp -r "$half"/. "$data"/ || exit 4
[ -d "$repo/.whl" ] || [ ! -d "$stash/whl" ] || cp -r "$stash"/whl "$repo/.whl"
runs=${RUNS:-/tmp/ft_runs}
free_kb=$(df --output=avail -k /dev/shm 2>/dev/null | tail -n 1)
# the frame cache of a 600-demo recording is ~9 GB of .npy: memory, not disk, where it fits
if [ -z "${RUNS:-}" ] && [ -n "$free_kb" ] && [ "$free_kb" -gt 40000000 ]; then
  runs=/dev/shm/ft_runs
fi
echo "joined $(du -sh "$data" | cut -f1) in $data; runs in $runs; $((SECONDS - t0)) s"
[ -z "$mid" ] || [ ${#specs[@]} -lt 2 ] || echo "note: MID_STEP adds a policy to the" \
  "${#specs[@]} runs' and a call returns about two 28.6 MB policies: fetch what is left out" \
  "from $runs/*.tar in a next call on the warm machine"
RUNS=$runs bash "$here/finetune_on_gpu.sh" "$data" "$OUT" "$train_s" "${specs[@]}"
name=${specs[0]%%:*}
ck=$runs/$name/checkpoints/step_$(printf %07d "${mid:-0}")
if [ -n "$mid" ] && [ -d "$ck" ]; then
  pack=$runs/pack_mid && rm -rf "$pack" && mkdir -p "$pack" && cp "$ck"/pretrained_model/* "$pack"/
  "${PY:-python3}" -c 'import sys
from safetensors.torch import load_file, save_file
p = sys.argv[1] + "/model.safetensors"
save_file({k: v.half() if v.is_floating_point() else v for k, v in load_file(p).items()}, p)' "$pack"
  tar cf "$runs/mid.tar" -C "$pack" . && split -b 15000000 -d "$runs/mid.tar" "$OUT/mid$mid.tar."
fi
echo "call 2: $((SECONDS - t0)) s"

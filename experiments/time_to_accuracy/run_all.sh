#!/usr/bin/env bash
# The whole experiment: calibrate each (dataset, recipe) alone on the machine, then
# replay every run at the calibrated rate, two at a time, one core each.
#
#   bash experiments/time_to_accuracy/run_all.sh                # everything
#   DATASETS="pickup humans" SEEDS="0 1" bash experiments/time_to_accuracy/run_all.sh
#   TAG=_eq03925 SET="model.z_equivariance_rot_angle=0.3925" OUT_DIR=DIR RECIPES=cpu \
#     bash experiments/time_to_accuracy/run_all.sh   # a setting: recipe name cpu_eq03925
#
# Calibration runs (60 s of training, alone) go to OUT_DIR/calibration/; replayed runs
# to OUT_DIR (results/), the recipe's name followed by TAG, with the config overrides of
# SET (space-separated KEY=VALUE) on every replayed run. Then: python
# experiments/time_to_accuracy/report.py
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
HERE=experiments/time_to_accuracy
DATASETS=${DATASETS:-"drink face jaws pickup stretch yoga humans"}
RECIPES=${RECIPES:-"cpu official"}
SEEDS=${SEEDS:-"0"}
BUDGET=${BUDGET:-600}
OUT=${OUT_DIR:-$HERE/results}
TAG=${TAG:-}
SET_ARGS=()
for item in ${SET:-}; do SET_ARGS+=(--set "$item"); done
CAL=$OUT/calibration
mkdir -p "$CAL" "$HERE/logs"
failed=$(mktemp)  # one line per failed run: the script then exits 1

reuse_calibration() {  # D R: copy R's calibration of another sequence with D's number of points
  "$PY" - "$CAL" "$1" "$2" <<'PYEOF'
import glob, json, os, sys

sys.path.insert(0, "experiments/time_to_accuracy")
from run import sequence_path  # noqa: E402

from c3dpo_jax.data import importers  # noqa: E402

cal, dataset, recipe = sys.argv[1:]
if dataset == "humans":
    sys.exit(1)  # humans: K depends on its config; calibrate it itself
try:
    path = sequence_path(dataset)
except Exception:
    sys.exit(1)  # no such sequence: the calibration run below says so in its log
k = importers.load_sequence(path).shape[1]
for f in sorted(glob.glob(os.path.join(cal, f"*__{recipe}__s0.json"))):
    r = json.load(open(f))
    if r["n_keypoints"] == k and "calibrated_on" not in r and r["dataset"] != "humans":
        out = dict(r, dataset=dataset, calibrated_on=r["dataset"])
        json.dump(out, open(os.path.join(cal, f"{dataset}__{recipe}__s0.json"), "w"), indent=1)
        print(f"calibration of {dataset} / {recipe}: reusing {r['dataset']}'s (K = {k})")
        sys.exit(0)
sys.exit(1)
PYEOF
}

# The rate depends only on the recipe and the number of points K, so a sequence whose K
# matches an already calibrated one reuses that file (marked ``calibrated_on``;
# REUSE_CALIBRATION=0 calibrates every dataset itself).
for d in $DATASETS; do
  for r in $RECIPES; do
    f=$CAL/${d}__${r}__s0.json
    [ -f "$f" ] && continue
    [ "${REUSE_CALIBRATION:-1}" = 1 ] && reuse_calibration "$d" "$r" && continue
    "$PY" $HERE/run.py --dataset="$d" --recipe="$r" --budget_s=60 \
      --eval_every_s=60 --out_dir="$CAL" > "$HERE/logs/cal_${d}_${r}.log" 2>&1
  done
done

rate() {  # steps_per_s compile_s of a calibration file
  "$PY" -c "import json,sys; r=json.load(open(sys.argv[1])); print(r['steps_per_s'], r['compile_s'])" "$1"
}

# Small networks (PARALLEL_RECIPES) run two at a time, one core each: on this 2-core
# machine that gives ~1.4x the throughput of one run on both cores. Large ones (the
# official 1024 x 6 trunks) are ~5x slower on one core than on two, so they run alone.
PARALLEL_RECIPES=${PARALLEL_RECIPES:-"cpu"}
jobs_file=$(mktemp)
serial_file=$(mktemp)
for s in $SEEDS; do
  for r in $RECIPES; do
    for d in $DATASETS; do
      [ -f "$OUT/${d}__${r}${TAG}__s${s}.json" ] && continue
      read -r sps cs < <(rate "$CAL/${d}__${r}__s0.json")
      if [[ " $PARALLEL_RECIPES " == *" $r "* ]]; then
        echo "$d $r $s $sps $cs" >> "$jobs_file"
      else
        echo "$d $r $s $sps $cs" >> "$serial_file"
      fi
    done
  done
done

pop() {  # prints and removes the first job, atomically
  flock 9
  head -n 1 "$jobs_file"
  sed -i 1d "$jobs_file"
} 9> "$jobs_file.lock"

one() {  # one D R S SPS CS [taskset/XLA prefix...]
  local d=$1 r=$2 s=$3 sps=$4 cs=$5
  shift 5
  local log=$HERE/logs/${d}_${r}${TAG}_s${s}.log
  "$@" "$PY" $HERE/run.py --dataset="$d" --recipe="$r" --seed="$s" --budget_s="$BUDGET" \
    --steps_per_s="$sps" --compile_s="$cs" --out_dir="$OUT" --tag="$TAG" \
    ${SET_ARGS[@]+"${SET_ARGS[@]}"} < /dev/null > "$log" 2>&1 ||
    { echo "FAILED: $d $r $s (see $log)"; echo "$d $r $s" >> "$failed"; }
}

worker() {  # worker CORE: runs jobs from the shared queue on that core
  local core=$1 line
  while line=$(pop) && [ -n "$line" ]; do
    # shellcheck disable=SC2086
    one $line env XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
      taskset -c "$core"
  done
}
worker 0 & worker 1 & wait
while read -r line; do
  # shellcheck disable=SC2086
  one $line env
done < "$serial_file"
rm -f "$jobs_file" "$jobs_file.lock" "$serial_file"
if [ -s "$failed" ]; then
  echo "$(wc -l < "$failed") run(s) failed; their logs are in $HERE/logs" >&2
  rm -f "$failed"
  exit 1
fi
rm -f "$failed"
if [ "$OUT" = "$HERE/results" ] && [ -z "$TAG" ]; then "$PY" $HERE/report.py; fi

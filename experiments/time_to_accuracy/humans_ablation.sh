#!/usr/bin/env bash
# The synthetic-humans ablation of the README ("Why the synthetic humans degrade"):
# 2-minute replayed runs through the library's loop, the paper's objective with
# canonicalisation weight 1 (the setting that degrades on the built-in humans), seed 0,
# two at a time, one core each; results in results/humans_ablation/.
#   bash experiments/time_to_accuracy/humans_ablation.sh
#   python experiments/time_to_accuracy/report.py --results=experiments/time_to_accuracy/results/humans_ablation
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
HERE=experiments/time_to_accuracy
OUT=$HERE/results/humans_ablation
SEQ=$(mktemp -d)
trap 'rm -rf "$SEQ"' EXIT
"$PY" $HERE/make_humans_sequences.py "$SEQ"
run() {  # CORE ARGS...: one replayed 120 s run pinned to a core
  local core=$1
  shift
  XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
    taskset -c "$core" "$PY" $HERE/run.py --budget_s=120 --compile_s=10 --out_dir="$OUT" \
    --set loss.w_canonicalization=1.0 "$@" > /dev/null 2>&1 || echo "FAILED: $*"
}
# Sequences of one body / many bodies / a smooth path, views as for the mocap data
# (replayed at the K=41 calibration, 39.4 steps/s: 4,340 steps).
S=(--steps_per_s=39.4)
# The built-in humans (the K=17 calibration, 51 steps/s: 5,620 steps), without/with
# self-occlusion, proportions spread 1 / 0.5 / 0.
H=(--dataset=humans --eval_every_s=40 --steps_per_s=51)
P0=(--set data.humans.proportions=0.0)
run 0 --dataset="$SEQ/rand_fixed.npz" "${S[@]}" &
run 1 --dataset="$SEQ/path_fixed.npz" "${S[@]}" &
wait
run 0 --dataset="$SEQ/rand_var.npz" "${S[@]}" &
run 1 "${H[@]}" --tag=_w1 &
wait
run 0 "${H[@]}" --self_occlusion=false --tag=_noocc &
run 1 "${H[@]}" --self_occlusion=false --set data.humans.proportions=0.5 --tag=_noocc_p05 &
wait
run 0 "${H[@]}" --self_occlusion=false "${P0[@]}" --tag=_noocc_p0 &
run 1 "${H[@]}" "${P0[@]}" --tag=_p0 &
wait
run 0 "${H[@]}" "${P0[@]}" --train_poses=3000 --tag=_p0_3k &
run 1 "${H[@]}" "${P0[@]}" --set optim.lr=1e-3 --tag=_p0_lr1e3 &
wait
# The library's default loss (the early deformation prior of configs/own_json.py) on the
# default bodies, and 100 surface points (K = 117; replayed at 40 steps/s: 4,400 steps).
run 0 "${H[@]}" --set loss.w_deformation=1.0 --set loss.w_deformation_final=0.0 \
  --set "loss.deformation_ramp=(1000,2000)" --tag=_w1_prior &
run 1 --dataset=humans --eval_every_s=40 --steps_per_s=40 --set data.humans.dense_points=100 \
  --tag=_dense100 &
wait

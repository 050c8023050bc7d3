#!/usr/bin/env bash
# The synthetic-humans ablation of the README ("Why the synthetic humans fail"): 2-minute
# replayed runs of the cpu recipe, seed 0, one core each, results in results/search/.
#   bash experiments/time_to_accuracy/humans_ablation.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
HERE=experiments/time_to_accuracy
OUT=$HERE/results/search
SEQ=$(mktemp -d)
"$PY" $HERE/make_humans_sequences.py "$SEQ"
run() {  # CORE ARGS...: one replayed 120 s run pinned to a core
  local core=$1
  shift
  taskset -c "$core" "$PY" $HERE/run.py --budget_s=120 --compile_s=10 --out_dir="$OUT" "$@" \
    > /dev/null 2>&1
}
# Sequences of one body / many bodies / a smooth path, views as for the mocap data
# (replayed at the K=41 calibration, 39.4 steps/s: 4,340 steps).
run 0 --dataset="$SEQ/rand_fixed.npz" --steps_per_s=39.4 &
run 1 --dataset="$SEQ/path_fixed.npz" --steps_per_s=39.4 &
wait
run 0 --dataset="$SEQ/rand_var.npz" --steps_per_s=39.4 &
# The built-in humans (K=17 calibration, 51 steps/s: 5,620 steps), inputs scaled to unit
# RMS radius (keypoint_rescale 1.9), without/with self-occlusion, proportions spread 1/0.5/0.
# loss.w_canonicalization=1: the ablation ran before configs/humans.py set 10.
H=(--dataset=humans --eval_every_s=40 --steps_per_s=51 --set model.keypoint_rescale=1.9
   --set loss.w_canonicalization=1.0)
run 1 "${H[@]}" --self_occlusion=false --tag=_noocc_r19 &
wait
run 0 "${H[@]}" --self_occlusion=false --set data.humans.proportions=0.0 --tag=_noocc_r19_p0 &
run 1 "${H[@]}" --self_occlusion=false --set data.humans.proportions=0.5 --tag=_noocc_r19_p05 &
wait
run 0 "${H[@]}" --set data.humans.proportions=0.0 --tag=_r19_p0 &
run 1 "${H[@]}" --set data.humans.proportions=0.0 --train_poses=3000 --tag=_r19_p0_3k &
wait
run 0 "${H[@]}" --set data.humans.proportions=0.0 --set loss.w_canonicalization=10.0 --tag=_r19_p0_wc10 &
run 1 "${H[@]}" --set data.humans.proportions=0.0 --set model.z_augment_rot_angle=3.14 --tag=_r19_p0_zaug &
wait
run 0 "${H[@]}" --set data.humans.proportions=0.0 --set optim.lr=1e-3 --tag=_r19_p0_lr1e3 &
run 1 --dataset=humans --eval_every_s=40 --steps_per_s=40 --set model.keypoint_rescale=1.9 \
  --set loss.w_canonicalization=1.0 --set data.humans.dense_points=100 --tag=_r19_dense100 &
wait
rm -rf "$SEQ"

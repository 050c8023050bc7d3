#!/usr/bin/env bash
# README command 1: set up (if needed), train C3DPO on the built-in dataset, evaluate.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m c3dpo_jax.main --config=configs/synthetic.py --workdir="${1:-runs/synthetic}"

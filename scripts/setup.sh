#!/usr/bin/env bash
# Creates .venv (if missing) and installs c3dpo_jax with its test and plotting extras.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.c3dpo_installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  # PYTHONWARNINGS reaches pip's build of the package: setuptools' notice that an editable
  # install exists would otherwise be the first thing the quick start prints.
  PYTHONWARNINGS=ignore .venv/bin/python -m pip install --quiet -e ".[test,viz]"
  touch "$stamp"
fi

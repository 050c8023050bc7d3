#!/usr/bin/env bash
# README command 2: set up (if needed) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check --quiet .  # lint: pyproject's [tool.ruff] rules (line length 100, imports)
# Two worker processes (pytest-xdist): most of the suite is XLA compilation, which uses
# one core at a time, so two workers keep both cores of a small machine busy.
exec .venv/bin/python -m pytest -n "${PYTEST_WORKERS:-2}" --dist worksteal "$@"

#!/usr/bin/env bash
# Set up and run the whole test suite (lint, types, dead code, unit, end-to-end and fault-injection tests).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
ruff check src tests bench scripts
mypy
vulture src/mira scripts/vulture_allow.py --min-confidence 60  # dead code; what stays is listed there, with why
export OMP_NUM_THREADS=1
python -m pytest -q -p no:cacheprovider tests "$@"

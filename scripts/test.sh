#!/usr/bin/env bash
# Set up and run the whole test suite (lint, types, unit, end-to-end and fault-injection tests).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
ruff check src tests bench scripts
mypy
export OMP_NUM_THREADS=1
python -m pytest -q -p no:cacheprovider tests "$@"

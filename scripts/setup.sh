#!/usr/bin/env bash
# Install MIRA and everything it needs into the active Python environment (a virtualenv is fine).
# The pinned CPU PyTorch wheel goes in first so that nothing pulls a multi-GB CUDA build;
# the package itself asks only for a minimum torch, which this wheel satisfies.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --upgrade pip
python -c "import torch" 2>/dev/null || python -m pip install --quiet "torch==2.13.0"
python -m pip install --quiet -e ".[dev,ray,video]"

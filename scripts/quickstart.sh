#!/usr/bin/env bash
# Set up and run the main job on its embedded default: a short run on HalfCheetah-v5 with the
# episodic (sparse) reward setting, no network and no API key needed.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mira train --task halfcheetah --method dense --algo sac --steps 20000 --learning-starts 5000 \
  --eval-every 5000 --eval-episodes 5 --seed 0 --out runs/quickstart --overwrite "$@"

#!/usr/bin/env bash
# Set up and run the main job on its embedded default: MIRA on HalfCheetah-v5 in the episodic
# (sparse-reward) setting, with the offline rule-based reward engineer (no network, no API key),
# then print the story of the run. The outer loop runs on short cycles (ΔT = 1,000 steps, short
# warm-up, one cycle above the threshold is enough to trigger) so that monitoring and reframing show
# within minutes. Each trigger has SRR propose three edits, check and verify them, and install the
# best one that passes the proxy test, or back off. Which happens depends on the CPU model (float
# rounding, and with it the run's path, differs between models; one machine reproduces a run exactly).
# What a user may see is in README.md ("What the quick start shows"). Table 1's
# defaults are ΔT = 5,000, a 10-cycle warm-up and two cycles in a row above the threshold (drop the
# --set flags for those). One intra-op thread: with two, any other job on a 2-core machine stalls
# every OpenMP barrier (docs/results.md, Speed).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mira train --task halfcheetah --method mira --algo sac --steps 20000 --learning-starts 2000 \
  --eval-every 2500 --eval-episodes 3 --seed 1 --threads 1 --out runs/quickstart --overwrite \
  --set mira.mcm.delta_t=1000 --set mira.mcm.k_warm=3 --set mira.mcm.buffer_min=3 \
  --set mira.mcm.min_scores=3 --set mira.mcm.min_history=3 --set mira.mcm.k_cool=3 \
  --set mira.mcm.n_consecutive=1 --set mira.holdout_episodes=1 "$@"
mira explain runs/quickstart

#!/usr/bin/env bash
# Learning benchmark for a many-core machine: {dense, sparse, hars, mira} x seeds with `mira train`, plus
# Stable-Baselines3's SAC on the dense reward, one core per run; then the learning table
# (bench/learning.py) and an experiment report (`mira report`) of the MIRA runs.
#
#   OUT=/tmp/out bash bench/many_core_learning.sh                       # defaults below
#   STEPS=2000 LS=500 EVERY=1000 EPISODES=1 SEEDS=0 WORKERS=2 LIMIT=120 OUT=/tmp/out bash bench/many_core_learning.sh
#
# WHEELS=dir installs missing packages from pre-downloaded wheels first (for a machine without an index).
# LIMIT bounds the training wall time: runs still going then are stopped and reported at the step they reached.
# The results (table.md, report/ and the run directories without checkpoints) are packed into $OUT/learning.tgz.
set -uo pipefail
cd "$(dirname "$0")/.."
: "${OUT:?set OUT to a directory for the results}"
STEPS=${STEPS:-25000}
LS=${LS:-5000}
EVERY=${EVERY:-2500}
EPISODES=${EPISODES:-5}
SEEDS=${SEEDS:-0,1,2}
METHODS=${METHODS:-dense,sparse,hars,mira}
WORKERS=${WORKERS:-15}
LIMIT=${LIMIT:-480}
RUNS=${RUNS:-bench/runs/learning}
# MCM scaled to a short budget: a cycle per evaluation, three cycles of warm-up (the paper's ΔT = 5000 and
# K_warm = 10 need 50k steps before the first possible trigger).
MIRA_ARGS=${MIRA_ARGS:-"--set mira.mcm.delta_t=$EVERY --set mira.mcm.k_warm=3 --set mira.mcm.buffer_min=3 --set mira.mcm.min_scores=3"}

if [[ -n "${WHEELS:-}" ]]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site:$PWD/src
fi
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
python3 - <<'EOF'
import os, platform, torch, gymnasium, mujoco
print(f"python {platform.python_version()}, torch {torch.__version__}, gymnasium {gymnasium.__version__}, "
      f"mujoco {mujoco.__version__}, {os.cpu_count()} cpus")
EOF
lscpu | grep -E "Model name|^CPU\(s\)|Thread\(s\) per core" || true
mkdir -p "$OUT" "$RUNS"

started=$(date +%s)
timeout -s TERM "$LIMIT" python3 bench/learning.py --methods "$METHODS" --sb3 --seeds "$SEEDS" --steps "$STEPS" \
  --learning-starts "$LS" --eval-every "$EVERY" --eval-episodes "$EPISODES" --workers "$WORKERS" --out "$RUNS" \
  --train-args "$MIRA_ARGS" > "$OUT/bench.log" 2>&1
echo "training exit $? after $(( $(date +%s) - started )) s"
python3 bench/learning.py --table-only --methods "$METHODS" --seeds "$SEEDS" --steps "$STEPS" --learning-starts "$LS" \
  --eval-every "$EVERY" --eval-episodes "$EPISODES" --workers "$WORKERS" --out "$RUNS" --train-args "$MIRA_ARGS"
shopt -s nullglob
ours=("$RUNS"/{dense,sparse,hars,mira}-sac-s*)
python3 -m mira.cli report "${ours[@]}" --out "$RUNS/report" --include-incomplete 2>&1 | tail -3
tar czf "$OUT/learning.tgz" --exclude=checkpoints -C "$(dirname "$RUNS")" "$(basename "$RUNS")"
ls -la "$OUT"

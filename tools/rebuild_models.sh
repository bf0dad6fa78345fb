#!/usr/bin/env bash
# Rebuild the shipped models from scratch, reproducibly for a seed:
#   1. simulate the paper's data set (Table I campaign) and the two Magny-Cours laps,
#   2. train the paper-faithful recipe and the improved one, export ONNX + model cards,
#   3. evaluate both (Table IV protocols, baselines) into models/evaluation.{json,md}.
# Usage: tools/rebuild_models.sh [WORK_DIR]   (SEED=N to change the seed; ~10 min on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-build/rebuild}"
seed="${SEED:-0}"
rm -rf "$work"
mkdir -p "$work" models
virtsensor campaign paper --out "$work/paper" --seed "$seed" --quiet
virtsensor simulate magny-cours --speed 180 --mu 1.0 --seed "$seed" --out "$work/magny-cours.csv"
virtsensor train --data "$work/paper" --recipe paper --out models/paper.onnx --seed "$seed"
virtsensor train --data "$work/paper" --recipe improved --out models/improved.onnx --seed "$seed"
virtsensor evaluate --model models/improved.onnx --data "$work/paper" --track "$work/magny-cours.csv" \
    --seed "$seed" --json models/evaluation.json --markdown models/evaluation.md

#!/usr/bin/env bash
# Rebuild the shipped models from scratch, reproducibly for a seed:
#   1. simulate the paper's data set (Table I campaign), track driving on random circuits (campaign
#      'circuits': no surveyed circuit), and, with another seed, the circuits no model ever trains on:
#      the two Magny-Cours laps (the report circuit) and the development circuits, dry and wet;
#   2. train the paper-faithful recipe on the Table I data only, and the improved one on Table I plus
#      the random circuits; export ONNX + model cards;
#   3. evaluate: Table IV protocols and baselines into models/evaluation.{json,md} (test rows and
#      held-out runs from Table I only; a row per unseen circuit), with the shipped model file scored on
#      the laps and circuits inside and outside its validity envelope.
# Usage: tools/rebuild_models.sh [WORK_DIR]   (SEED=N for the training seed; ~30 min on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-build/rebuild}"
seed="${SEED:-0}"
unseen_seed="${UNSEEN_SEED:-7}"
rm -rf "$work"
mkdir -p "$work/unseen" models
virtsensor campaign paper --out "$work/paper" --seed "$seed" --quiet
virtsensor campaign circuits --out "$work/circuits" --seed "$seed" --quiet
virtsensor simulate magny-cours --speed 180 --mu 1.0 --seed "$unseen_seed" --out "$work/magny-cours.csv"
for track in hungaroring zandvoort red-bull-ring; do
    for mu in 1.0 0.7; do
        virtsensor simulate circuit --track "$track" --speed 180 --mu "$mu" --seed "$unseen_seed" \
            --out "$work/unseen/${track}_mu${mu}.csv"
    done
done
virtsensor train --data "$work/paper" --recipe paper --out models/paper.onnx --seed "$seed"
virtsensor train --data "$work/paper" "$work/circuits" --recipe improved --out models/improved.onnx --seed "$seed"
virtsensor evaluate --model models/improved.onnx --data "$work/paper" --train-extra "$work/circuits" \
    --track "$work/magny-cours.csv" --circuits "$work"/unseen/*.csv --seed "$seed" \
    --json models/evaluation.json --markdown models/evaluation.md

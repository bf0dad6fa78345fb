#!/usr/bin/env bash
# Rebuild the shipped models from scratch, reproducibly for a seed:
#   1. simulate the paper's data set (Table I campaign), track driving on random circuits (campaign
#      'circuits': no surveyed circuit), and, with another seed, the circuits no model ever trains on:
#      the two Magny-Cours laps (the report circuit) and the development circuits, dry and wet;
#   2. train the paper-faithful recipe on the Table I data only, and the improved one on Table I plus
#      the random circuits; export ONNX + model cards;
#   3. evaluate: Table IV protocols and baselines into models/evaluation.{json,md} (test rows and
#      held-out runs from Table I only; a row per unseen circuit), with the shipped model file scored on
#      the laps and circuits inside and outside its validity envelope;
#   4. TPMS (issue 17): the same presets with each run's four tyre pressures drawn around nominal (three
#      Table I seeds and the random circuits), the TPMS recipe trained on them with the improved model as
#      its pressure-free fallback (models/tpms.onnx), and the pressure protocol in the evaluation: whole
#      held-out runs (the Table I campaign with the unseen seed) at 1.8, 2.2 and 2.8 bar, pressure-free and
#      TPMS models side by side.
# The pressure-free models train on the car's own (nominal) pressures, as before (--car-pressures).
# Usage: tools/rebuild_models.sh [WORK_DIR]   (SEED=N for the training seed; ~45 min on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-build/rebuild}"
seed="${SEED:-0}"
unseen_seed="${UNSEEN_SEED:-7}"
rm -rf "$work"
mkdir -p "$work/unseen" models
virtsensor campaign paper --out "$work/paper" --seed "$seed" --car-pressures --quiet
virtsensor campaign circuits --out "$work/circuits" --seed "$seed" --car-pressures --quiet
mkdir -p "$work/tpms" "$work/pressure"
for s in 0 1 2; do
    virtsensor campaign paper --out "$work/tpms/paper-$s" --seed "$((seed + s))" --quiet
done
virtsensor campaign circuits --out "$work/tpms/circuits" --seed "$seed" --quiet
for p in 1.8 2.2 2.8; do
    virtsensor campaign paper --out "$work/pressure/p$p" --seed "$unseen_seed" --pressure-bar "$p" --quiet
done
virtsensor simulate magny-cours --speed 180 --mu 1.0 --seed "$unseen_seed" --out "$work/magny-cours.csv"
for track in hungaroring zandvoort red-bull-ring; do
    for mu in 1.0 0.7; do
        virtsensor simulate circuit --track "$track" --speed 180 --mu "$mu" --seed "$unseen_seed" \
            --out "$work/unseen/${track}_mu${mu}.csv"
    done
done
virtsensor train --data "$work/paper" --recipe paper --out models/paper.onnx --seed "$seed"
virtsensor train --data "$work/paper" "$work/circuits" --recipe improved --out models/improved.onnx --seed "$seed"
virtsensor train --data "$work"/tpms/* --recipe tpms --fallback models/improved.onnx --out models/tpms.onnx \
    --seed "$seed"
virtsensor evaluate --model models/improved.onnx --data "$work/paper" --train-extra "$work/circuits" \
    --track "$work/magny-cours.csv" --circuits "$work"/unseen/*.csv --seed "$seed" \
    --tpms-model models/tpms.onnx --pressure-runs "$work"/pressure/p* --pressure-train "$work"/tpms/* \
    --json models/evaluation.json --markdown models/evaluation.md

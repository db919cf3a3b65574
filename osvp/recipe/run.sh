#!/usr/bin/env bash
# The osvp recipe end to end: generate a training set, train `small`, measure it on its validation
# samples, then plan on meshes it never saw. From the repository root with the venv active:
#   bash osvp/recipe/run.sh [WORK_DIR]          (default: recipe-work)
# Results of a real run: osvp/recipe/RESULTS.md.
set -euo pipefail
work=${1:-recipe-work}
epochs=${EPOCHS:-25}
lambda=${LAMBDA:-2}
objects=$(bash osvp/recipe/objects.sh "$work")

echo "== 1. training set: 40 objects x 8 rotations, POCO refiner (osvp/recipe/training.toml)"
time datagen submit --objects "$objects" --config osvp/recipe/training.toml --out "$work/train-data"

echo "== 2. train osvp small on 2 CPU threads, lambda $lambda, 80/20 split of the samples"
time osvp train --data "$work/train-data" --out "$work/osvp-small" --preset small --epochs "$epochs" \
  --lambda "$lambda" --threads 2

echo "== 3. precision / recall / F1 of the best epoch: held-out samples, then trained-on ones (the paper's protocol)"
time osvp eval --data "$work/train-data" --checkpoint "$work/osvp-small/best.pt" --split val --threads 2
time osvp eval --data "$work/train-data" --checkpoint "$work/osvp-small/best.pt" --split train --threads 2

echo "== 4. plan on the six watertight shared meshes, none of them in the training set"
time datagen evaluate --objects examples/watertight-meshes.txt --planner "osvp:$work/osvp-small/best.pt" \
  --planner oracle --planner greedy --planner greedy:10 --planner random \
  --rotations 0,4 --initial-views 0,8,16,24 --per-object --png "$work/figures/unseen.png"

#!/usr/bin/env bash
# The osvp recipe end to end: generate a training set, train `small` on it with an ambiguity-aware
# target, measure it on the samples of held-out objects, then plan on meshes it never saw beside
# the dataset's own labels and random views at equal view counts. From the repository root with the
# venv active:
#   bash osvp/recipe/run.sh [WORK_DIR]          (default: recipe-work)
# Results of a real run: osvp/recipe/RESULTS.md.
set -euo pipefail
work=${1:-recipe-work}
steps=${STEPS:-10000}
lambda=${LAMBDA:-2}
target=${TARGET:-mincover}
decoding=${DECODING:-tuned}
objects=$(bash osvp/recipe/objects.sh "$work")

echo "== 1. training set: 86 objects x 8 rotations, POCO refiner (osvp/recipe/training.toml)"
time datagen submit --objects "$objects" --config osvp/recipe/training.toml --out "$work/train-data"

echo "== 2. train osvp small on 2 CPU threads: target $target, lambda $lambda, $steps steps, 6 objects held out"
time osvp train --data "$work/train-data" --out "$work/osvp-small" --preset small --target "$target" \
  --lambda "$lambda" --steps "$steps" --split objects --val-fraction 0.07 --threads 2

echo "== 3. the held-out objects' samples: F1 against the stored label and the nearest minimum cover, per decoding"
time osvp eval --data "$work/train-data" --checkpoint "$work/osvp-small/best.pt" --split val --threads 2

echo "== 4. plan on the six watertight shared meshes, none of them in the training set"
planner="osvp+$decoding:$work/osvp-small/best.pt"
time datagen evaluate --objects examples/watertight-meshes.txt --planner "$planner" \
  --planner "random:match=$planner" --planner oracle --planner random --planner greedy:10 \
  --rotations 0,4 --initial-views 0,8,16,24 --per-object --png "$work/figures/unseen.png"

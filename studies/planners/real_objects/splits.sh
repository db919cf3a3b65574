#!/usr/bin/env bash
# The real-object split of issue 49, by mesh: the 227 scans of ../shared/corpus and the shared meshes,
# test about 20 % and validation about 10 % of each source folder (ycb, kit, household, meshes), seed 49.
# The six watertight meshes and the eight high-ceiling meshes are evaluation sets: --hold keeps them
# out of every split, so nothing here trains on them. Run from anywhere; writes beside this script:
#   corpus.txt, meshes.txt (the scans), train.txt, val.txt, test.txt (paths relative to this folder).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../../.." && pwd)"
shared="$root/../shared"
cd "$here"
datagen objects scan "$shared/corpus" --check --out corpus.txt
datagen objects scan "$shared/meshes" --check --out meshes.txt
datagen objects split corpus.txt meshes.txt --out . --seed 49 --test 0.2 --val 0.1 \
  --hold "$root/examples/watertight-meshes.txt" --hold "$root/examples/high-ceiling-meshes.txt"

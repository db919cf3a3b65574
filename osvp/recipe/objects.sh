#!/usr/bin/env bash
# Writes the recipe's training objects file: the 22 built-ins, SYNTH seeded synthetic shapes (default
# 40, `datagen objects synth --seed 7`: the first N of a larger set are the N-set) and the 24 shared
# meshes of training-shared-meshes.txt (86 objects). Usage: objects.sh WORK_DIR
set -euo pipefail
work=$(realpath -m "$1")
synth=${SYNTH:-40}
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
mkdir -p "$work"
datagen objects synth --count "$synth" --seed 7 --out "$work/synth" >/dev/null
{
  echo "# osvp recipe training objects (written by osvp/recipe/objects.sh)"
  grep '^builtin:' "$root/examples/builtin.txt"
  grep -v '^#' "$work/synth/objects.txt" | sed "s|^|$work/synth/|"
  grep -v '^#' "$here/training-shared-meshes.txt" | sed "s|^\.\./\.\./\.\./shared|$(realpath -m "$root/../shared")|"
} > "$work/training-objects.txt"
echo "$work/training-objects.txt"

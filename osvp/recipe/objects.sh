#!/usr/bin/env bash
# Writes the recipe's training objects file: the 22 built-ins, 11 seeded synthetic shapes and the 7
# shared meshes of training-shared-meshes.txt (40 objects). Usage: objects.sh WORK_DIR
set -euo pipefail
work=$(realpath -m "$1")
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
mkdir -p "$work"
datagen objects synth --count 11 --seed 7 --out "$work/synth" >/dev/null
{
  echo "# osvp recipe training objects (written by osvp/recipe/objects.sh)"
  grep '^builtin:' "$root/examples/builtin.txt"
  grep -v '^#' "$work/synth/objects.txt" | sed "s|^|$work/synth/|"
  grep -v '^#' "$here/training-shared-meshes.txt" | sed "s|^\.\./\.\./\.\./shared|$(realpath -m "$root/../shared")|"
} > "$work/training-objects.txt"
echo "$work/training-objects.txt"

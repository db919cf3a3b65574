#!/usr/bin/env bash
# The datasets of issue 49, made with the service itself into WORK (default ../real-work beside the checkout):
#   real-{train,val}-none  the split's training and validation objects, 8 rotations, refiner none, default voxel
#   synth200-none          the first 200 of 1,000 synthetic objects (seed 23), 2 rotations, refiner none:
#                          the learning curve's pre-training (runs.sh scvp-nb-synth200-2k)
#   synth1000-none         all 1,000 of them (scvp-nb-synth-4k; mixed into the real ones by scvp-nb-8k-mix25)
#   real-train-none-r16    the training objects at 16 rotations, refiner none: the label-true augmentation
#                          (the 32 views have no symmetry, view_symmetry.py), for scvp-nb-8k-r16
#   real-train-poco        the training objects at the paper's settings (the default config: POCO, 8
#                          rotations, default voxel); beside real-train-none, the refinement comparison
#                          (the paper's cover labels of the same cases, with and without POCO)
#   real-{train,val}-none-tau90  relabels for the one-shot planner: partial cover at tau 0.9 (judged on
#                          what the views see, so the same whichever refiner made the dataset)
#   real-val-poco          the validation objects at the paper's settings
# Each line is one `datagen submit`; running the script again resumes what is not done (committed tasks
# are kept, never recomputed). The none datasets come first: they train the next-view planners in minutes,
# whose labels do not depend on the refiner (docs/pipeline.md section 8.1).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
work="${1:-$here/../../../../real-work}"
mkdir -p "$work"
printf 'refiner = "none"\n' > "$work/none.toml"
printf 'refiner = "none"\nrotations = 2\n' > "$work/synth.toml"
submit() { echo "== $(date -u +%FT%TZ) $*"; datagen submit "$@"; }
submit --objects "$here/train.txt" --config "$work/none.toml" --out "$work/real-train-none"
submit --objects "$here/val.txt" --config "$work/none.toml" --out "$work/real-val-none"
[ -f "$work/synth/objects.txt" ] || datagen objects synth --count 1000 --seed 23 --out "$work/synth"
grep -v '^#' "$work/synth/objects.txt" | head -200 > "$work/synth/objects-200.txt"  # the learning curve's pre-training
submit --objects "$work/synth/objects-200.txt" --config "$work/synth.toml" --out "$work/synth200-none"
submit --objects "$work/synth/objects.txt" --config "$work/synth.toml" --out "$work/synth1000-none"
printf 'refiner = "none"\nrotations = 16\n' > "$work/none-r16.toml"
submit --objects "$here/train.txt" --config "$work/none-r16.toml" --out "$work/real-train-none-r16"
submit --objects "$here/train.txt" --out "$work/real-train-poco"
datagen shards card "$work/real-train-poco" --objects "$here/train.txt"  # its card: the corpus's sources and licences
relabel() { datagen shards relabel "$work/$1" --out "$work/$2" "${@:3}"; }  # resumes a stopped relabel
relabel real-train-none real-train-none-tau90 --objective partial_cover --tau 0.9 --workers 2
relabel real-val-none real-val-none-tau90 --objective partial_cover --tau 0.9 --workers 2
submit --objects "$here/val.txt" --out "$work/real-val-poco"
echo "== $(date -u +%FT%TZ) done"

#!/usr/bin/env bash
# The refinement comparison's twins, into WORK (default ../real-work beside the checkout): the 171
# training objects at one rotation, made with POCO version 2 (the paper's refiner at the default voxel),
# with no refiner, and with POCO version 4 (issue 50: its labels judged against version 2's). Their
# cover labels train the same one-shot planner (runs.sh cover-{none,poco,poco4}-r1-2k). Resumable, as
# datasets.sh. One rotation is an eighth of the paper's 8 (datasets.sh's real-train-poco: 3.3 CPU-hours).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
work="${1:-$here/../../../../real-work}"
mkdir -p "$work"
printf 'refiner = "none"\nrotations = 1\n' > "$work/none-r1.toml"
printf 'rotations = 1\npoco_version = 2\n' > "$work/poco-r1.toml"  # the hash of the version-2 default's
printf 'rotations = 1\npoco_version = 4\n' > "$work/poco4-r1.toml"
printf '# the defaults: POCO, 8 rotations (judge.py --config images the POCO planner with it)\n' > "$work/poco.toml"
submit() { echo "== $(date -u +%FT%TZ) $*"; datagen submit "$@"; }
submit --objects "$here/train.txt" --config "$work/none-r1.toml" --out "$work/real-train-none-r1"
submit --objects "$here/train.txt" --config "$work/poco-r1.toml" --out "$work/real-train-poco-r1"
submit --objects "$here/train.txt" --config "$work/poco4-r1.toml" --out "$work/real-train-poco4-r1"
echo "== $(date -u +%FT%TZ) done"

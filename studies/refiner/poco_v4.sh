#!/usr/bin/env bash
# POCO version 4's candidate weights (issue 50), trained and judged into WORK (default ../real-work):
#   poco_v4.sh WORK train [MINUTES]   train (resumable: run again to continue; MINUTES a call, default 45)
#                                     and export datagen/data/poco_fast.pt (poco_version 4's weights)
#   poco_v4.sh WORK judge             results/poco-v4-eval-{test,six}.md: `datagen poco eval` of version 2's
#                                     weights and the candidate on objects neither saw; and
#                                     benchmarks/generation/results/task-cost-v4.md: both in one task_cost run
#   poco_v4.sh WORK planners          the labels and the planners they train, against version 2's:
#                                     studies/labels/results/version-labels-4.md (the oracle, two seeds) and
#                                     results/poco-v4-planners-{v2,v4}.md (the one-shot planner trained at two seeds
#                                     on each version's cover labels of the 171 training objects at one
#                                     rotation, judged on the real test split); resumable
# The candidate: the `fast_sv` preset (decoder K 16, 1,500 encoder input points; small_sv's weight
# shapes), started from the shipped version-2 weights and trained on the 22 built-ins, 40 synthetic
# shapes and the watertight meshes of the real-object split's training objects
# (studies/planners/real_objects/train.txt; its test and validation objects are never seen).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
work="${1:-$root/../real-work}"
phase="${2:-train}"
run="$work/poco-v4"
weights="$root/datagen/data/poco_fast.pt"  # a new export is another file: version 4's sha256 is pinned (tests/pipeline/test_poco_version_4.py)
split="$root/studies/planners/real_objects"

train() {
  local resume=() init=()
  if [ -f "$run/last.pt" ]; then resume=(--resume); else init=(--init "$root/datagen/data/poco_small.pt"); fi
  echo "== $(date -u +%FT%TZ) train"
  datagen poco train --out "$run" --preset fast_sv --seed 4 --tasks 480 --samples-per-task 4 --synth 40 \
    --objects "$split/train.txt" --steps 100000 --threads 1 \
    --checkpoint-every 100 --max-minutes "${1:-45}" "${init[@]}" "${resume[@]}"
  echo "== $(date -u +%FT%TZ) export"
  datagen poco export --run "$run" --out "$weights" --seed 4
}

threshold() {  # the candidate's threshold, tuned at export on the run's held-out shapes
  python -c "import json, sys, torch; print(json.loads(torch.load(sys.argv[1], weights_only=True)['extra'])['threshold'])" "$weights"
}

eval_report() {  # $1 objects file, $2 report
  local cut; cut="$(threshold)"
  {
    echo "# POCO version 2 and the version-4 candidate on single views of objects neither was trained on"
    echo
    echo "Written by \`bash studies/refiner/poco_v4.sh WORK judge\` ($(date -u +%F), $(git -C "$root" rev-parse --short HEAD)): the two commands below."
    echo
    echo '```'
    echo "\$ datagen poco eval --objects ${1#"$root/"} --weights builtin"
    COLUMNS=140 datagen poco eval --objects "$1" --weights builtin
    echo
    echo "\$ datagen poco eval --objects ${1#"$root/"} --weights ${weights#"$root/"} --threshold $cut"
    COLUMNS=140 datagen poco eval --objects "$1" --weights "$weights" --threshold "$cut"
    echo '```'
  } > "$2"
}

judge() {
  local cut; cut="$(threshold)"
  printf 'poco_version = 4\n' > "$work/poco-v4.toml"  # its weights, preset fast_sv and threshold (schemas.config.POCO_VERSIONS)
  printf 'poco_version = 2\n' > "$work/poco-v2.toml"
  echo "== $(date -u +%FT%TZ) eval"
  eval_report "$split/test.txt" "$here/results/poco-v4-eval-test.md"
  eval_report "$root/examples/watertight-meshes.txt" "$here/results/poco-v4-eval-six.md"
  echo "== $(date -u +%FT%TZ) task cost"
  (cd "$root" && python -m benchmarks.generation.task_cost --objects builtin:capsule builtin:mug builtin:torus_knot_3_5 \
    --configs "$work/poco-v2.toml" "$work/poco-v4.toml" --floor-repeats 1 \
    --out benchmarks/generation/results/task-cost-v4.md --replace)
}

planners() {
  local real="$root/studies/planners/real_objects"
  echo "== $(date -u +%FT%TZ) labels"
  (cd "$root" && python -m studies.labels.version_labels --versions 2 4 --seeds 0 1 --workers 2) > "$work/version-labels-4.txt"
  echo "== $(date -u +%FT%TZ) datasets"
  bash "$real/twins.sh" "$work"  # real-train-{none,poco,poco4}-r1
  echo "== $(date -u +%FT%TZ) trainings"
  bash "$real/runs.sh" "$work" cover-poco-r1-2k cover-poco-r1-2k-s1 cover-poco4-r1-2k cover-poco4-r1-2k-s1
  echo "== $(date -u +%FT%TZ) judge"
  local version
  for version in 2 4; do  # each version's planners are played with the refiner that made their labels
    printf 'poco_version = %s\n' "$version" > "$work/poco$version.toml"
    local suffix=""; [ "$version" = 4 ] && suffix=4
    (cd "$root" && python -m studies.planners.real_objects.judge --set test --fixed-from "$work/real-train-none-r1" \
      --planner "v$version-seed0=osvp:$work/runs/cover-poco$suffix-r1-2k/best.pt" \
      --planner "v$version-seed1=osvp:$work/runs/cover-poco$suffix-r1-2k-s1/best.pt" \
      --config "$work/poco$version.toml" --work "$work/judge" --workers 2 \
      --out "studies/refiner/results/poco-v4-planners-v$version.md" --replace)
  done
}

case "$phase" in
  train) train "${3:-45}" ;;
  judge) judge ;;
  planners) planners ;;
  *) echo "usage: poco_v4.sh WORK train [MINUTES] | judge | planners" >&2; exit 2 ;;
esac
echo "== $(date -u +%FT%TZ) done"

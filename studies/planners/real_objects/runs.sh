#!/usr/bin/env bash
# Every training run of the real-object study (issue 49), on the datasets of datasets.sh in WORK.
# Usage: runs.sh WORK [RUN ...]   (no RUN: all of them). A finished run (its folder holds done) is
# skipped; a killed one resumes from its last.pt. One thread each: two runs side by side on 2 cores.
set -euo pipefail
work="${1:?usage: runs.sh WORK [RUN ...]}"; shift
here="$(cd "$(dirname "$0")" && pwd)"
runs="$work/runs"; mkdir -p "$runs"
train_none=("--data" "$work/real-train-none" "--val-data" "$work/real-val-none")

recipe() {  # the osvp train arguments of a run, by name
  case "$1" in
    # next-best-view planners on the real objects, refiner none (their labels do not depend on it)
    nbvnet-bv-4k)  echo "${train_none[*]} --network nbvnet --target best_view --steps 4000" ;;
    pcnbv-gain-4k) echo "${train_none[*]} --network osvp --target gain --source observed --steps 4000" ;;
    nbvnet-nb-4k)  echo "${train_none[*]} --network nbvnet --target near_best --steps 4000" ;;
    nbvnet-nb-8k)  echo "${train_none[*]} --network nbvnet --target near_best --steps 8000" ;;
    scvp-nb-8k)    echo "${train_none[*]} --network scvp --target near_best --steps 8000" ;;
    nbvnet-nb-cb5-8k) echo "${train_none[*]} --network nbvnet --target near_best --steps 8000 --case-balance 0.5" ;;
    scvp-nb-cb5-8k)   echo "${train_none[*]} --network scvp --target near_best --steps 8000 --case-balance 0.5" ;;
    # shipped:nbv's recipe at a second seed (the seeds' spread of its share) and at the paper's network
    # size (fully connected widths 1500 / 500 / 100 against the small preset's 512 / 256)
    scvp-nb-8k-s1)    echo "${train_none[*]} --network scvp --target near_best --steps 8000 --seed 1" ;;
    scvp-nb-8k-paper) echo "${train_none[*]} --network scvp --target near_best --steps 8000 --preset paper" ;;
    # the same at 16 rotations of the same objects (equal steps: each sample seen half as often), and with a
    # quarter of every epoch drawn from the 1,000 synthetic objects (osvp train --mix-data)
    scvp-nb-8k-r16)   echo "--data $work/real-train-none-r16 --val-data $work/real-val-none --network scvp --target near_best --steps 8000" ;;
    scvp-nb-8k-mix25) echo "${train_none[*]} --network scvp --target near_best --steps 8000 --mix-data $work/synth1000-none --mix-fraction 0.25" ;;
    scvp-nb-8k-mix10) echo "${train_none[*]} --network scvp --target near_best --steps 8000 --mix-data $work/synth1000-none --mix-fraction 0.1" ;;
    # shipped:nbv (scvp-nb-8k, its best epoch the last) trained 8,000 steps more at half the learning rate
    scvp-nb-8k-more)  echo "${train_none[*]} --network scvp --target near_best --steps 8000 --lr 0.0005 --init $here/../../../osvp/src/osvp/shipped/nbv.pt" ;;
    # one-shot planners: partial cover at tau 0.9 (label-margin.md's best one-shot objective)
    pcnbv-nb-8k)   echo "${train_none[*]} --network osvp --target near_best --source observed --steps 8000" ;;
    oneshot-mc-8k) echo "--data $work/real-train-none-tau90 --val-data $work/real-val-none-tau90 --network osvp --target mincover --steps 8000" ;;
    # the same labels and steps for SCVP's own grid network (with the view state): the grid networks are the
    # ones that generalised as next-best-view planners
    scvp-mc-8k)    echo "--data $work/real-train-none-tau90 --val-data $work/real-val-none-tau90 --network scvp --target mincover --steps 8000" ;;
    # the same, fine-tuned from shipped:nbv (the same network and preset, trained for the next view): pre-training for the one-shot family
    scvp-mc-8k-init) echo "--data $work/real-train-none-tau90 --val-data $work/real-val-none-tau90 --network scvp --target mincover --steps 8000 --init $here/../../../osvp/src/osvp/shipped/nbv.pt" ;;
    # the real-object learning curve (scvp near_best, the shipped nbv's recipe, at 1,000 steps): 25, 50,
    # 100 and all 171 training objects (--max-objects draws nested seeded subsets), from random weights
    # and fine-tuned from the planner pre-trained on the 1,000 synthetic objects
    scvp-nb-synth-4k) echo "--data $work/synth1000-none --val-data $work/real-val-none --network scvp --target near_best --steps 4000" ;;
    # the pre-training of the curve's -init points: the first 200 synthetic objects (synth200-none), 2,000 steps
    scvp-nb-synth200-2k) echo "--data $work/synth200-none --val-data $work/real-val-none --network scvp --target near_best --steps 2000" ;;
    lc-*-scratch|lc-*-init)
      n="${1#lc-}"; n="${n%-*}"; init=""
      [ "${1##*-}" = init ] && init="--init $runs/scvp-nb-synth200-2k/best.pt"
      all=""; [ "$n" = all ] || all="--max-objects $n"
      echo "${train_none[*]} --network scvp --target near_best --steps 1000 $all $init" ;;
    # does refinement buy learning value? the paper's one-shot planner on the paper's cover labels of the
    # same cases, made with POCO (real-train-poco: the paper's settings) and with no refiner, equal steps
    # and seed, each validated on its own labels of the same held-out training objects (--split objects)
    cover-none-4k) echo "--data $work/real-train-none --network osvp --target mincover --steps 4000 --split objects --val-fraction 0.1" ;;
    cover-poco-4k) echo "--data $work/real-train-poco --network osvp --target mincover --steps 4000 --split objects --val-fraction 0.1" ;;
    # the paper's setting at the twins' steps: 8 rotations of POCO labels against cover-poco-r1-2k's one
    cover-poco-2k) echo "--data $work/real-train-poco --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1" ;;
    # the same comparison on the one-rotation twins (twins.sh: the CPU of a POCO dataset at 8 rotations
    # is 4.7 hours on 2 cores; one rotation of the same 171 objects is an eighth of it)
    cover-none-r1-2k) echo "--data $work/real-train-none-r1 --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1" ;;
    cover-poco-r1-2k) echo "--data $work/real-train-poco-r1 --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1" ;;
    # POCO version 4's labels of the same cases against version 2's (issue 50), at two seeds each
    cover-poco4-r1-2k) echo "--data $work/real-train-poco4-r1 --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1" ;;
    cover-poco-r1-2k-s1) echo "--data $work/real-train-poco-r1 --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1 --seed 1" ;;
    cover-poco4-r1-2k-s1) echo "--data $work/real-train-poco4-r1 --network osvp --target mincover --steps 2000 --split objects --val-fraction 0.1 --seed 1" ;;
    *) echo "unknown run $1" >&2; return 1 ;;
  esac
}

all=(nbvnet-bv-4k pcnbv-gain-4k nbvnet-nb-4k nbvnet-nb-8k scvp-nb-8k nbvnet-nb-cb5-8k scvp-nb-cb5-8k pcnbv-nb-8k oneshot-mc-8k)
for name in "${@:-${all[@]}}"; do
  out="$runs/$name"
  [ -f "$out/done" ] && continue
  resume=(); [ -f "$out/last.pt" ] && resume=(--resume)
  # shellcheck disable=SC2046
  osvp train $(recipe "$name") --out "$out" --threads 1 "${resume[@]}" > "$runs/$name.log" 2>&1
  touch "$out/done"
done

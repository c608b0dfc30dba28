#!/usr/bin/env bash
# Test MAE of DepthNet 64 px against training samples (docs/results/scaling/README.md):
#   docs/results/scaling/run.sh SEED STEPS_PER_EPOCH... [RUNS=runs/scaling]
# One run per STEPS_PER_EPOCH: 22 epochs of that many steps of 32 on data/stillbox-64-jpg, one
# torch thread, lr 0.01 x 0.3 at epochs 8, 12, 18, 21 (the 55-epoch schedule's 19, 30, 44, 53
# scaled: the recipe's milestones are fractions of --epochs), then `stillbox-bench eval` of the
# last checkpoint on the test split. 22 epochs rather than 55 keep the validations' cost small.
set -euo pipefail
SEED=$1 ; shift
RUNS=${RUNS:-runs/scaling} D=${DATA:-data/stillbox-64-jpg} B=.venv/bin/stillbox-bench EPOCHS=22
mkdir -p "$RUNS"
for steps in "$@"; do
  out=$RUNS/ours-e$steps-s$SEED resume=()
  [[ -f $out/checkpoints/last.pt ]] && resume=(--resume)
  SECONDS=0
  $B run depthnet --data "$D" --epochs $EPOCHS --epoch-size "$steps" --batch-size 32 \
    --threads 1 --seed "$SEED" --quiet --out "$out" "${resume[@]}" > "$out.log" 2>&1
  echo "$out trained in $SECONDS s" >> "$RUNS/times.txt"
  $B eval --ckpt "$out/checkpoints/last.pt" --data "$D" --out "$RUNS/eval/ours-e$steps-s$SEED" \
    > /dev/null 2>&1
done

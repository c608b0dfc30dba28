#!/usr/bin/env bash
# DepthNet 64 px trained in float32 and under bfloat16 autocast (--amp), same samples and seed,
# scored on the test split (docs/results/amp/README.md).
#   docs/results/amp/run.sh SEED fp32|bf16 [RUNS]
# 18 epochs of 171 steps of 32 (98,496 samples) of the 55-epoch reference schedule (lr 0.01,
# first decay at epoch 19: none within these 18), one torch thread, data/stillbox-64-jpg
# (stillbox-gen --res 64 --scenes 3000 --legacy --image-format jpg).
set -euo pipefail
SEED=$1 MODE=$2 RUNS=${3:-runs/amp}
B=${BENCH:-.venv/bin/stillbox-bench} D=${DATA:-data/stillbox-64-jpg}
case $MODE in fp32) AMP=--no-amp ;; bf16) AMP=--amp ;; *) echo "mode: fp32 or bf16" >&2; exit 2 ;; esac
OUT=$RUNS/$MODE-s$SEED
mkdir -p "$RUNS"
SECONDS=0
$B run depthnet --data "$D" --epochs 55 --epoch-size 171 --max-steps 3078 --batch-size 32 \
  --threads 1 --seed "$SEED" "$AMP" --quiet --out "$OUT" > "$OUT.log" 2>&1
echo "$OUT trained in $SECONDS s" >> "$RUNS/times.txt"
$B eval --ckpt "$OUT/checkpoints/last.pt" --data "$D" --out "$RUNS/eval/$MODE-s$SEED" >> "$OUT.log" 2>&1

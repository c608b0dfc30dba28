#!/usr/bin/env bash
# The author's DepthNet code against ours at equal budget (docs/results/reference/README.md).
#   docs/results/reference/run.sh CODE PYTHON SEED LAST_EPOCH [RUNS]
# CODE: your checkout of github.com/ClementPinard/DepthNet; PYTHON: a Python that runs it.
# Both codes train on data/stillbox-64-jpg (stillbox-gen --res 64 --scenes 3000 --legacy
# --image-format jpg) with one torch thread each, side by side: 55 epochs of 171 steps of 32
# (300,960 samples), lr 0.01 x 0.3 at epochs 19, 30, 44, 53, stopped after LAST_EPOCH; the
# checkpoints after KEEP epochs are scored by `stillbox-bench eval` on the test split.
set -euo pipefail
CODE=$1 PY=$2 SEED=$3 LAST=$4 RUNS=${5:-runs/reference}
D=${DATA:-data/stillbox-64-jpg} B=.venv/bin/stillbox-bench
EPOCH_SIZE=${EPOCH_SIZE:-171} BATCH=32
read -ra KEEP <<< "${KEEP:-6 12 18 19 29 43 55}"
keep=() ; for e in "${KEEP[@]}"; do ((e <= LAST)) && keep+=("$e"); done

author() {
  .venv/bin/python -m benchmark.supervised.reference train --code "$CODE" --python "$PY" \
    --data "$D" --out "$RUNS/author-s$SEED" --keep "$(IFS=,; echo "${keep[*]}")" --threads 1 -- \
    --bn --activation-function elu --lr 0.01 -b $BATCH -j 0 --epochs "$LAST" \
    --epoch-size $EPOCH_SIZE --seed "$SEED" --print-freq 1000 > "$RUNS/author-s$SEED.log" 2>&1
}

ours() {
  local out=$RUNS/ours-s$SEED resume=()
  for e in "${keep[@]}"; do
    $B run depthnet --data "$D" --epochs 55 --epoch-size $EPOCH_SIZE --batch-size $BATCH \
      --threads 1 --seed "$SEED" --max-steps $((e * EPOCH_SIZE)) --quiet --out "$out" \
      "${resume[@]}" >> "$RUNS/ours-s$SEED.log" 2>&1
    mkdir -p "$out/epochs" && cp "$out/checkpoints/last.pt" "$out/epochs/epoch$e.pt"
    resume=(--resume)
  done
}

mkdir -p "$RUNS"
SECONDS=0; author & ours; wait
echo "trained in $SECONDS s" >> "$RUNS/times-s$SEED.txt"
for e in "${keep[@]}"; do
  .venv/bin/python -m benchmark.supervised.reference convert \
    "$RUNS/author-s$SEED/epochs/epoch$e.pth.tar" --data "$D" --out "$RUNS/author-s$SEED/epochs/epoch$e.pt"
  for who in author ours; do
    $B eval --ckpt "$RUNS/$who-s$SEED/epochs/epoch$e.pt" --data "$D" \
      --out "$RUNS/eval/$who-s$SEED-e$e" > /dev/null 2>&1
  done
done

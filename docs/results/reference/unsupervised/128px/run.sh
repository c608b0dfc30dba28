#!/usr/bin/env bash
# The author's chapter-5 code at 128 px (README.md beside): train_img_pairs.py, unmodified but for
# ../launcher.py's substitutions, on the rotating 128 px StillBox of docs/results/unsup-128 for 10
# epochs of 200 steps of 16 five-frame sequences (one torch thread), each epoch's checkpoints
# converted to a depthnet-unsup checkpoint and scored by `stillbox-bench eval-sequences`.
#   docs/results/reference/unsupervised/128px/run.sh CODE PYTHON [RUNS]
# CODE: your checkout of github.com/ClementPinard/unsupervised-depthnet; PYTHON: a Python that
# runs it (see ../README.md). Run from the repository root.
set -euo pipefail
CODE=$1 PY=$2 RUNS=${3:-runs/ref-unsup-128}
D=data/stillbox-rot-128
H=docs/results/reference/unsupervised/harness.py
B=.venv/bin/stillbox-bench P=.venv/bin/python
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
[ -f "$D/manifest.parquet" ] || .venv/bin/stillbox-gen --preset stillbox-rotating --res 128 \
  --scenes 240 --out "$D"
mkdir -p "$RUNS"
$P $H prepare "$D" "$RUNS/author-layout"
SECONDS=0
$P $H train "$CODE" "$PY" "$RUNS/author-layout" "$RUNS/author" -- \
  --dataset-format StillBox --sequence-length 5 --supervise-pose --with-gt --bn depth \
  -b 16 -j 0 --epochs 10 --epoch-size 200 --training-milestones 0 0 \
  --lr 2e-4 --momentum 0.9 --beta 0.999 --weight-decay 0 \
  --ssim 0.15 -s 3.0 --kappa 5.1 --nominal-displacement 0.3 --seed 0 --print-freq 50 \
  > "$RUNS/author.log" 2>&1
echo "author: $SECONDS s" >> "$RUNS/times.txt"
E=$RUNS/author/epochs
for k in $(seq 1 10); do
  $P $H convert "$E/epoch${k}_depthnet.pth.tar" "$E/epoch${k}_posenet.pth.tar" "$D" \
    "$RUNS/author/epoch$k.pt"
  $B eval-sequences --ckpt "$RUNS/author/epoch$k.pt" --data "$D" --quiet \
    --out "$RUNS/eval-author-e$k"
done

#!/usr/bin/env bash
# The author's chapter-5 code against ours at equal budget (docs/results/reference/unsupervised/README.md).
#   docs/results/reference/unsupervised/run.sh CODE PYTHON [RUNS]
# CODE: your checkout of github.com/ClementPinard/unsupervised-depthnet; PYTHON: a Python that
# runs it (torch 2.13 CPU, imageio, path, tensorboardX, blessings, progressbar2, scikit-image,
# matplotlib). Both codes train one after the other, one torch thread each, for 500 steps of 16
# 5-frame sequences on data/stillbox-rot-64, then both are scored by `stillbox-bench eval-sequences`.
set -euo pipefail
CODE=$1 PY=$2 RUNS=${3:-runs/ref-unsup}
D=${DATA:-data/stillbox-rot-64}
H=docs/results/reference/unsupervised/harness.py
B=.venv/bin/stillbox-bench P=.venv/bin/python
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
[ -f "$D/manifest.parquet" ] || nice -n 10 .venv/bin/stillbox-gen --preset stillbox-rotating \
  --res 64 --scenes 800 --out "$D" --workers 1 --threads 1
mkdir -p "$RUNS"

# ours: the Table 5.2 row "unsupervised DepthNet (P, O)" (--log-every 1 only logs every step)
SECONDS=0
nice -n 10 $B run depthnet-unsup --pose orientation --data "$D" --batch-size 16 --max-steps 500 \
  --threads 1 --log-every 1 --quiet --out "$RUNS/ours" > "$RUNS/ours.log" 2>&1
echo "ours: $SECONDS s" >> "$RUNS/times.txt"

# the author's train_img_pairs.py on the same train/val scenes (harness.py prepare writes its layout)
$P $H prepare "$D" "$RUNS/author-layout"
SECONDS=0
nice -n 10 $P $H train "$CODE" "$PY" "$RUNS/author-layout" "$RUNS/author" -- \
  --dataset-format StillBox --sequence-length 5 --supervise-pose --with-gt --bn depth \
  -b 16 -j 0 --epochs 1 --epoch-size 500 --training-milestones 0 0 \
  --lr 2e-4 --momentum 0.9 --beta 0.999 --weight-decay 0 \
  --ssim 0.15 -s 3.0 --kappa 5.1 --nominal-displacement 0.3 --seed 0 --print-freq 50 \
  > "$RUNS/author.log" 2>&1
echo "author: $SECONDS s" >> "$RUNS/times.txt"

# the author's checkpoint as one of ours, checked against the author's networks, then both scored
E=$RUNS/author/epochs
$P $H convert "$E/epoch1_depthnet.pth.tar" "$E/epoch1_posenet.pth.tar" "$D" "$RUNS/author/author.pt"
$P $H verify "$CODE" "$E/epoch1_depthnet.pth.tar" "$E/epoch1_posenet.pth.tar" "$RUNS/author/author.pt" \
  > "$RUNS/verify.json"
nice -n 10 $B eval-sequences --ckpt "$RUNS/ours/checkpoints/best.pt" --ckpt "$RUNS/ours/checkpoints/last.pt" \
  --ckpt "$RUNS/author/author.pt" --data "$D" --quiet --out "$RUNS/table"
$P $H curves "$RUNS/ours/steps.csv" "$(ls "$RUNS"/author/checkpoints/*/*/progress_log_full.csv)" "$RUNS/curves"

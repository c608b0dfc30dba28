#!/usr/bin/env bash
# Table 5.2's unsupervised rows at 128 px, each trained from scratch for the same 400 steps of 16
# five-frame sequences (4 epochs of 100 steps, one torch thread) on rotating 128 px StillBox, then
# scored together by eval-sequences (thesis pair rule "P" and the fixed pair, PoseNet's cosine).
# Run from the repository root:  docs/results/table-5.2-128/run.sh [RUNS]
# The "unsupervised DepthNet (P, O)" row at the same budget is the orientation run of
# docs/results/unsup-128 (its epoch 4), the supervised row that folder's supervised DepthNet.
# STILLBOX_BENCH / STILLBOX_GEN: the commands to use (default: stillbox-bench / stillbox-gen).
set -euo pipefail
RUNS=${1:-runs/table-5.2-128}
B=${STILLBOX_BENCH:-stillbox-bench}
G=${STILLBOX_GEN:-stillbox-gen}
DATA=data/stillbox-rot-128
[ -f "$DATA/manifest.parquet" ] || $G --preset stillbox-rotating --res 128 --scenes 240 --out "$DATA"
A="--data $DATA --batch-size 16 --epoch-size 100 --epochs 4 --threads 1 --ckpt-every 100000 --quiet"
train() {  # NAME MODEL OPTIONS...: one row, timed
    local name=$1 model=$2
    shift 2
    [ -f "$RUNS/$name/checkpoints/last.pt" ] && [ -f "$RUNS/$name.seconds" ] && return
    SECONDS=0
    # shellcheck disable=SC2086
    $B run "$model" "$@" $A --out "$RUNS/$name"
    echo "$SECONDS" > "$RUNS/$name.seconds"
}
mkdir -p "$RUNS"
train unsup-O-odm depthnet-unsup --pose orientation --occlusion
train unsup-6dof depthnet-unsup-6dof
train sfm sfmlearner --pose orientation
$B eval-sequences --ckpt "$RUNS/unsup-O-odm/checkpoints/last.pt" \
    --ckpt "$RUNS/unsup-6dof/checkpoints/last.pt" --ckpt "$RUNS/sfm/checkpoints/last.pt" \
    --data "$DATA" --quiet --out "$RUNS/table"

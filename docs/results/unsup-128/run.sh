#!/usr/bin/env bash
# depthnet-unsup at 128 px from scratch: a time-boxed learning curve, scored under Table 5.2's
# protocol. Run from the repository root:
#   docs/results/unsup-128/run.sh MODE [EPOCHS] [RUNS]
# MODE orientation:  rotating StillBox (240 scenes of 20 frames), the dataset's rotations and
#                    PoseNet's translations in the warps (Table 5.2's "O" row)
# MODE occlusion:    orientation with the occlusion module (Table 5.2's "O, occlusion" row)
# MODE 6dof:         rotating StillBox, depthnet-unsup-6dof: PoseNet's rotations and translations
#                    in the warps, no supervision at all (Table 5.2's 6-DoF row)
# MODE sfmlearner:   rotating StillBox, sfmlearner with the dataset's rotations (Table 5.2's
#                    SFMLearner row, here with the orientation known)
# MODE known-motion: stabilised StillBox (600 scenes of 10 frames), the dataset's translations in
#                    the warps instead of PoseNet's (a control: can DepthNet learn here at all?)
# EPOCHS: epochs of 100 steps of 16 sequences (10); RUNS: where run folders go (runs/unsup-128).
# Writes RUNS/MODE/O (the run), RUNS/MODE/kept/epoch_K.pt (the checkpoint after each epoch's
# validation) and RUNS/MODE/eval-epoch_K (eval-sequences, with the constant plane, and for
# known-motion also `eval` on the test pairs) for each K in $EVAL_EPOCHS (default: every epoch).
# STILLBOX_BENCH / STILLBOX_GEN: the commands to use (default: stillbox-bench / stillbox-gen).
# PRETRAINED: a checkpoint to start from (`run --pretrained`: the networks' weights, a fresh
# optimiser), e.g. a known-motion run's last epoch to continue it past its planned epochs.
# SMOOTH_WEIGHT: λ of the smooth loss (`run --smooth-weight`; 0: the photometric term alone).
# POSE_WARMUP: first steps with the DepthNet frozen, PoseNet alone learning (`run --pose-warmup`).
# LR: the learning rate (`run --lr`; default: the recipe's, 2e-4), e.g. lower to continue a run
# from its last epoch with PRETRAINED.
# POSE_LR: PoseNet's learning rate (`run --pose-lr`; default: the recipe's, as the depth network's).
# SCENES: rotating scenes to train the rotating modes on (240). Another count trains on
# data/stillbox-rot-128-SCENES (scenes of the same seed: a scene and its split depend only on its
# index) and still scores on the test split of data/stillbox-rot-128, so the constant and the
# test sequences stay those of every other run here (none of them in any training split).
# THREADS: torch CPU threads of the training run (1).
# RESUME=1: continue the run in RUNS/MODE/O to EPOCHS (`run --resume`, the same options; more
# epochs than it was started with are allowed, the recipe having no milestones).
set -euo pipefail
MODE=${1:?usage: run.sh orientation|occlusion|6dof|sfmlearner|known-motion [EPOCHS] [RUNS]}
EPOCHS=${2:-10}
RUNS=${3:-runs/unsup-128}/$MODE
B=${STILLBOX_BENCH:-stillbox-bench}
G=${STILLBOX_GEN:-stillbox-gen}
MODEL=depthnet-unsup
case $MODE in
orientation | occlusion | 6dof | sfmlearner)
    EVAL_DATA=data/stillbox-rot-128
    [ -f "$EVAL_DATA/manifest.parquet" ] ||
        $G --preset stillbox-rotating --res 128 --scenes 240 --out "$EVAL_DATA"
    SCENES=${SCENES:-240}
    DATA=$EVAL_DATA
    [ "$SCENES" = 240 ] || DATA=$EVAL_DATA-$SCENES
    [ -f "$DATA/manifest.parquet" ] ||
        $G --preset stillbox-rotating --res 128 --scenes "$SCENES" --out "$DATA"
    case $MODE in
    orientation) OPTIONS="--pose orientation" ;;
    occlusion) OPTIONS="--pose orientation --occlusion" ;;
    6dof) MODEL=depthnet-unsup-6dof OPTIONS="" ;;
    sfmlearner) MODEL=sfmlearner OPTIONS="--pose orientation" ;;
    esac ;;
known-motion)
    DATA=data/stillbox-128
    [ -f "$DATA/manifest.parquet" ] || $G --res 128 --scenes 600 --out "$DATA"
    EVAL_DATA=$DATA
    OPTIONS="--known-motion" ;;
*)
    echo "run.sh: MODE must be orientation, occlusion, 6dof, sfmlearner or known-motion," \
        "got '$MODE'" >&2
    exit 2 ;;
esac
mkdir -p "$RUNS/kept"
# shellcheck disable=SC2086
$B run $MODEL $OPTIONS --data "$DATA" --batch-size 16 --epoch-size 100 \
    --epochs "$EPOCHS" --ckpt-every 100000 --threads "${THREADS:-1}" --quiet --out "$RUNS/O" \
    ${PRETRAINED:+--pretrained "$PRETRAINED"} ${SMOOTH_WEIGHT:+--smooth-weight "$SMOOTH_WEIGHT"} \
    ${POSE_WARMUP:+--pose-warmup "$POSE_WARMUP"} ${POSE_LR:+--pose-lr "$POSE_LR"} \
    ${LR:+--lr "$LR"} ${RESUME:+--resume} &
run=$!
rows() { echo $(($(cat "$RUNS/O/metrics.csv" 2>/dev/null | wc -l) - 1)); }
seen=0
[ -n "${RESUME:-}" ] && seen=$(rows)  # the epochs already kept
while kill -0 $run 2>/dev/null; do  # keep the checkpoint written at each validation
    sleep 20
    if [ "$(rows)" -gt "$seen" ]; then
        sleep 15  # last.pt is written after the metrics row
        seen=$(rows)
        cp "$RUNS/O/checkpoints/last.pt" "$RUNS/kept/epoch_$seen.pt"
    fi
done
wait $run
[ "$(rows)" -gt "$seen" ] && cp "$RUNS/O/checkpoints/last.pt" "$RUNS/kept/epoch_$(rows).pt"
for k in ${EVAL_EPOCHS:-$(seq 1 "$(rows)")}; do
    out=$RUNS/eval-epoch_$k
    [ -f "$out/results.csv" ] || $B eval-sequences --ckpt "$RUNS/kept/epoch_$k.pt" \
        --data "$EVAL_DATA" --quiet --out "$out"
    if [ "$MODE" = known-motion ] && [ ! -f "$out-pairs/summary.json" ]; then
        $B eval --ckpt "$RUNS/kept/epoch_$k.pt" --data "$EVAL_DATA" --out "$out-pairs"
    fi
done

#!/usr/bin/env bash
# Table 5.2 at 128 px at the setting where an unsupervised row first beat the constant plane:
# each unsupervised row trained from scratch on the 1,519 training scenes of the 1,900-scene
# rotating set for 5,800 steps of 16 five-frame sequences (58 epochs of 100 steps), the
# supervised DepthNet for 30 epochs of 151 steps of 32 pairs: on the stabilised
# data/stillbox-128 (supervised) and, as the thesis' "D + O", on the same rotating training
# scenes with each pair's reference stabilised by the known orientation (supervised-rotating);
# all scored together by eval-sequences on the 416 test sequences of data/stillbox-rot-128
# (pair rule "P", fixed pair, PoseNet's cosine). Run from the repository root:
#   docs/results/table-5.2-128/run-5800.sh [ROWS]
# ROWS: the rows to train, of supervised supervised-rotating orientation occlusion 6dof sfmlearner
# (all of them).
# Each unsupervised row is docs/results/unsup-128/run.sh MODE 58 runs/unsup-128-1900 (its
# checkpoints kept and scored every 4 epochs); a row already at 58 epochs is not trained again,
# an unfinished one continues (RESUME=1). The table is written once every row is done.
# STILLBOX_BENCH / STILLBOX_GEN: the commands to use; THREADS: torch CPU threads per run (2).
set -euo pipefail
ROWS=${*:-supervised supervised-rotating orientation occlusion 6dof sfmlearner}
B=${STILLBOX_BENCH:-stillbox-bench}
G=${STILLBOX_GEN:-stillbox-gen}
HERE=$(dirname "$0")
EPOCHS=58
RUNS=runs/unsup-128-1900
SUPERVISED=runs/sup-128-30
ROTATING=runs/sup-128-rot-30
export THREADS=${THREADS:-2} SCENES=1900 EVAL_EPOCHS="8 12 16 20 24 28 32 36 40 44 48 52 56 58"
epochs_done() { echo $(($(cat "$1/metrics.csv" 2>/dev/null | wc -l) - 1)); }
supervised() {  # DATA OUT [OPTIONS]: 30 epochs of 32, continued when unfinished
    local data=$1 out=$2
    shift 2
    [ "$(epochs_done "$out")" -ge 30 ] && return
    $B run depthnet --data "$data" --batch-size 32 --epochs 30 "$@" --threads "$THREADS" \
        --quiet --out "$out" $([ -f "$out/checkpoints/last.pt" ] && echo --resume)
}
for row in $ROWS; do
    case $row in
    supervised)
        [ -f data/stillbox-128/manifest.parquet ] ||
            $G --res 128 --scenes 600 --out data/stillbox-128
        supervised data/stillbox-128 "$SUPERVISED" ;;  # an epoch: one pass, 151 steps
    supervised-rotating)
        [ -f data/stillbox-rot-128-1900/manifest.parquet ] || $G --preset stillbox-rotating \
            --res 128 --scenes 1900 --out data/stillbox-rot-128-1900  # as run.sh's SCENES=1900
        supervised data/stillbox-rot-128-1900 "$ROTATING" --epoch-size 151 ;;
    orientation | occlusion | 6dof | sfmlearner)
        done_=$(epochs_done "$RUNS/$row/O")
        [ "$done_" -ge "$EPOCHS" ] && continue
        RESUME=$([ "$done_" -gt 0 ] && echo 1 || true) \
            "$HERE/../unsup-128/run.sh" "$row" "$EPOCHS" "$RUNS" ;;
    *) echo "run-5800.sh: unknown row '$row'" >&2; exit 2 ;;
    esac
done
ckpts=()
for ckpt in "$SUPERVISED/checkpoints/best.pt" "$ROTATING/checkpoints/best.pt" \
    "$RUNS"/{orientation,occlusion,6dof,sfmlearner}/kept/epoch_$EPOCHS.pt; do
    [ -f "$ckpt" ] || { echo "run-5800.sh: $ckpt missing; the table waits for every row" >&2; exit 0; }
    ckpts+=(--ckpt "$ckpt")
done
$B eval-sequences "${ckpts[@]}" --data data/stillbox-rot-128 --quiet --out runs/table-5.2-128-5800

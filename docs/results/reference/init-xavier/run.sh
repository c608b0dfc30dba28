#!/usr/bin/env bash
# Our DepthNet with the author's initialisation (torch's xavier_normal_ on every convolution
# weight) instead of ours, for the first 12 epochs of the 300 K schedule (55 epochs of 171 steps
# of 32), checkpoints of epochs 6 and 12 scored on the test split
# (docs/results/reference/README.md, "Initialisation: the author's xavier_normal"):
#   docs/results/reference/init-xavier/run.sh SEED [RUNS]
# The changed line lives in a copy of this commit's tree in a temporary folder (the working tree
# is never edited); RUNS (default runs/xavier) receives the run and its evals.
set -euo pipefail
SEED=$1
RUNS=$(realpath -m "${2:-runs/xavier}") D=$(realpath data/stillbox-64-jpg) PY=$(realpath .venv/bin/python)
TREE=$(mktemp -d)
trap 'rm -rf "$TREE"' EXIT
git archive HEAD | tar -x -C "$TREE"
"$PY" - "$TREE/benchmark/core/models.py" <<'EOF'
import sys
path = sys.argv[1]
text = open(path).read()
ours = """        fan_out = conv.kernel_size[0] * conv.kernel_size[1] * conv.out_channels
        nn.init.normal_(conv.weight, 0.0, math.sqrt(2.0 / fan_out))"""
assert text.count(ours) == 1, "DepthNet.init_weight changed: update this script"
open(path, "w").write(text.replace(ours, "        nn.init.xavier_normal_(conv.weight)"))
EOF
out=$RUNS/ours-s$SEED resume=()
mkdir -p "$RUNS"
cd "$TREE"
for e in 6 12; do
  "$PY" -m benchmark.cli run depthnet --data "$D" --epochs 55 --epoch-size 171 --batch-size 32 \
    --threads 1 --seed "$SEED" --max-steps $((e * 171)) --quiet --out "$out" "${resume[@]}" \
    >> "$out.log" 2>&1
  mkdir -p "$out/epochs" && cp "$out/checkpoints/last.pt" "$out/epochs/epoch$e.pt"
  resume=(--resume)
done
for e in 6 12; do
  "$PY" -m benchmark.cli eval --ckpt "$out/epochs/epoch$e.pt" --data "$D" \
    --out "$RUNS/eval/xavier-s$SEED-e$e" > /dev/null 2>&1
done

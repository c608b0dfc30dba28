#!/usr/bin/env bash
# The small outputs behind the published numbers, from the run folders of run.sh:
#   docs/results/reference/outputs.sh RUNS OUT
# copies each scored checkpoint's summary.json, our runs' metrics.csv and config.json, and the
# author's runs' per-epoch log and command line into OUT (no checkpoint, no data).
set -euo pipefail
RUNS=$1 OUT=$2
mkdir -p "$OUT"
for s in "$RUNS"/eval/*/summary.json; do
  cp "$s" "$OUT/$(basename "$(dirname "$s")").summary.json"
done
for run in "$RUNS"/ours-s*/; do
  name=$(basename "$run")
  cp "$run/metrics.csv" "$OUT/$name.metrics.csv"
  cp "$run/config.json" "$OUT/$name.config.json"
done
for run in "$RUNS"/author-s*/; do
  name=$(basename "$run")
  cp "$run/command.txt" "$OUT/$name.command.txt"
  cp "$(find "$run/Results" -name progress_log_summary.csv | head -1)" \
    "$OUT/$name.progress_log_summary.csv"
done

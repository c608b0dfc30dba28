#!/usr/bin/env bash
# Old and new generator code timed alternately in one sitting on one machine (issue 26).
#
#   bash docs/results/generator-speed/interleave.sh OLD_TREE NEW_TREE RES SCENES ROUNDS [OUT]
#
# OLD_TREE and NEW_TREE are source checkouts (e.g. `git worktree add /tmp/old <commit>`); both
# run with this venv's Python. Each round renders the same SCENES scenes at RES px with the old
# code, then the new (the order swaps every round, so drift hits both alike), into fresh folders
# under OUT (default /tmp/interleave), and prints each run's frames/s from its summary line,
# then the mean of each side and their ratio. The datasets of the last round are kept for a
# byte comparison (`diff -r` of their scene folders) and `stillbox-gen stats`.
set -euo pipefail
old=$1 new=$2 res=$3 scenes=$4 rounds=$5 out=${6:-/tmp/interleave}
py=${PYTHON:-$(cd "$(dirname "$0")/../../.." && pwd)/.venv/bin/python}
mkdir -p "$out"
run() {  # run TREE NAME: one generation, prints its frames/s (from TREE: its code, not ours)
    rm -rf "$out/$2"
    (cd "$1" && PYTHONPATH=$1 "$py" -m stillbox_gen.cli --res "$res" --scenes "$scenes" --out "$out/$2" \
        --quiet) >"$out/$2.log" 2>&1 || { cat "$out/$2.log" >&2; exit 1; }
    sed -n 's/.*(\([0-9.]*\) frames\/s rendered).*/\1/p' "$out/$2.log"
}
declare -a fo fn
for ((i = 0; i < rounds; i++)); do
    if ((i % 2 == 0)); then a=$(run "$old" old); b=$(run "$new" new); else b=$(run "$new" new); a=$(run "$old" old); fi
    fo+=("$a"); fn+=("$b")
    echo "round $((i + 1)): old $a frames/s, new $b frames/s"
done
python3 - "${fo[*]}" "${fn[*]}" <<'PY'
import sys
old, new = ([float(x) for x in s.split()] for s in sys.argv[1:3])
mo, mn = sum(old) / len(old), sum(new) / len(new)
print(f"mean: old {mo:.1f}, new {mn:.1f} frames/s; new/old {mn / mo:.2f}x "
      f"(per round: {', '.join(f'{b / a:.2f}' for a, b in zip(old, new))})")
PY

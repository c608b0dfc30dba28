"""The small outputs of one run.sh run, gathered for this folder (what the pages quote).

    python docs/results/unsup-128/collect.py RUNS/MODE OUT

RUNS/MODE is run.sh's folder of one mode (``O/``: the run; ``eval-epoch_K/``: eval-sequences of
epoch K's checkpoint). Writes into OUT: the run's ``config.json``, ``metrics.csv`` and
``steps.csv``; ``results.csv``, the ``eval-sequences`` rows of every scored epoch in epoch order
(the constant plane, which does not depend on the epoch, once, from the first); and each epoch's
``results.md`` as ``results-epoch_K.md``. Rows are copied as text: the numbers are the files'.
"""

from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path

#: eval-sequences' model column of the constant plane (the same rows at every epoch)
CONSTANT = "constant"


def scored_epochs(runs: Path) -> dict[int, Path]:
    """{epoch K: its eval-sequences folder} for every ``eval-epoch_K`` holding a results.csv."""
    found = {}
    for folder in runs.glob("eval-epoch_*"):
        m = re.fullmatch(r"eval-epoch_(\d+)", folder.name)
        if m and (folder / "results.csv").is_file():
            found[int(m.group(1))] = folder
    return dict(sorted(found.items()))


def read_lines(path: Path) -> list[str]:
    """The lines of ``path`` with their own line ends (csv's are CR LF)."""
    with open(path, newline="") as f:
        return f.read().splitlines(keepends=True)


def merged_rows(files: list[Path]) -> list[str]:
    """The header and rows of ``files`` (eval-sequences results.csv, same header), the constant
    plane's rows from the first file only; each line as it is in its file."""
    header = None
    rows: list[str] = []
    for k, path in enumerate(files):
        lines = read_lines(path)
        if header is None:
            header = lines[0]
        elif lines[0] != header:
            raise ValueError(f"{path}: its columns differ from {files[0]}'s")
        model = header.rstrip("\r\n").split(",").index("model")
        for line in lines[1:]:
            if k == 0 or line.split(",")[model] != CONSTANT:
                rows.append(line)
    return [header, *rows] if header is not None else []


def collect(runs: Path, out: Path) -> list[int]:
    """Gather ``runs`` into ``out`` (see the module's text); returns the scored epochs."""
    run, epochs = runs / "O", scored_epochs(runs)
    if not (run / "metrics.csv").is_file():
        raise FileNotFoundError(f"{run}: no metrics.csv (not a run.sh run folder)")
    if not epochs:
        raise FileNotFoundError(f"{runs}: no eval-epoch_K/results.csv")
    out.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "metrics.csv", "steps.csv"):
        shutil.copyfile(run / name, out / name)
    rows = merged_rows([folder / "results.csv" for folder in epochs.values()])
    with open(out / "results.csv", "w", newline="") as f:
        f.writelines(rows)
    for k, folder in epochs.items():
        shutil.copyfile(folder / "results.md", out / f"results-epoch_{k}.md")
    return list(epochs)


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        sys.exit("usage: collect.py RUNS/MODE OUT")
    try:
        epochs = collect(Path(argv[0]), Path(argv[1]))
    except (OSError, ValueError) as e:
        sys.exit(f"collect.py: {e}")
    print(f"{argv[1]}: epochs {', '.join(map(str, epochs))}")


if __name__ == "__main__":
    main(sys.argv[1:])

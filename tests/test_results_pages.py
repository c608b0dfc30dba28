"""The numbers quoted in the results pages are those of their committed outputs: each table row
of docs/results/scaling, reference, reference/unsupervised, table-5.2, unsup-128, amp and toy is
read back from the page and compared, at the page's precision, with the results.csv, fit.json,
results.json and eval summaries beside it."""

from __future__ import annotations

import csv
import json
import math
import re
import statistics
from pathlib import Path

import numpy
import pytest

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def _rows(page: Path, first_cell: str) -> list[list[str]]:
    """Cells of the markdown table rows of ``page`` whose first cell matches ``first_cell``."""
    rows = []
    for line in page.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and re.fullmatch(first_cell, cells[0]):
            rows.append(cells)
    return rows


def _csv(path: Path) -> list[dict]:
    return list(csv.DictReader(path.read_text().splitlines()))


class _Quoted(float):
    """A number read from a page, with the decimals it was printed with ("0.930": 3)."""

    decimals: int

    def __new__(cls, text: str) -> _Quoted:
        number = super().__new__(cls, text)
        number.decimals = len(text.split(".")[1]) if "." in text else 0
        return number


def _numbers(text: str) -> list[float]:
    """Every decimal number of a cell (signed; the pages' minus is U+2212), thousands separators
    and bold marks removed."""
    plain = text.replace(",", "").replace("*", "").replace("\u2212", "-")
    return [_Quoted(v) for v in re.findall(r"(?<![\d.])-?\d+\.\d+", plain)]  # 6.72-10.15: a range


def _shown(value: float, like: float) -> float:
    """``value`` rounded to the decimals ``like`` was printed with (2 unless it has 3)."""
    decimals = getattr(like, "decimals", None)
    if decimals is None:
        decimals = len(repr(like).split(".")[1]) if "." in repr(like) else 0
    return round(value, max(decimals, 2))


def _agree(quoted: list[float], measured: list[float]) -> None:
    assert len(quoted) == len(measured), (quoted, measured)
    for q, m in zip(quoted, measured, strict=True):
        assert q == pytest.approx(_shown(m, q), abs=1e-9), (quoted, measured)


def test_scaling_table_and_fits_match_results_csv_and_fit_json():
    page = RESULTS / "scaling" / "README.md"
    runs = {int(r["samples"]): r for r in _csv(RESULTS / "scaling" / "results.csv")}
    held_out = 1_321_760  # the longest run: not in the fit (its own test below)
    rows = [r for r in _rows(page, r"[\d,]+") if int(r[0].replace(",", "")) != held_out]
    assert [int(r[0].replace(",", "")) for r in rows] == sorted(runs)
    for cells in rows:
        run = runs[int(cells[0].replace(",", ""))]
        measured = [float(run[k]) for k in ("mae", "mre", "mle", "p1.25")]
        _agree([float(c) for c in cells[1:5]], measured)
    fits = json.loads((RESULTS / "scaling" / "fit.json").read_text())["fits"]
    for cells in _rows(page, r"power law.*"):
        fit = fits[
            "power law" if "floor" not in cells[0] else next(k for k in fits if "floor" in k)
        ]
        at = fit["mae_at_target"]
        measured = [fit["slope"], fit["sigma"], at["fit"], at["low"], at["high"]]
        _agree(_numbers(" ".join(cells[1:])), measured)


def test_reference_300k_table_matches_its_results_csv():
    page = RESULTS / "reference" / "README.md"
    table = page.read_text().split("## 300 K samples")[1].split("Second seed")[0]
    scored = {
        (r["code"], int(r["seed"]), int(r["epoch"])): r
        for r in _csv(RESULTS / "reference" / "schedule-171" / "results.csv")
    }
    rows = [
        line for line in table.splitlines() if re.match(r"\| \d+ \| (\*\*)?[\d,]+(\*\*)? \|", line)
    ]
    assert len(rows) == 7
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        epoch = int(cells[0])
        for code, cell in (("author", cells[2]), ("ours", cells[3])):
            r = scored[(code, 0, epoch)]
            measured = [float(r[k]) for k in ("mae", "mre", "mle", "depth_error")]
            _agree(_numbers(cell), measured)


def test_reference_initialisation_table_matches_its_summaries():
    page = RESULTS / "reference" / "README.md"
    section = page.read_text().split("## Initialisation")[1].split("\n## ")[0]
    for line in section.splitlines():
        match = re.match(r"\| ([\d,]+) \|", line)
        if not match:
            continue
        samples = int(match.group(1).replace(",", ""))
        xavier = line.strip("|").split("|")[3]
        measured = []
        for seed in (0, 1):
            path = RESULTS / "reference" / "init-xavier" / f"xavier-s{seed}-e{samples // 5472}"
            s = json.loads(path.with_suffix(".summary.json").read_text())
            assert s["training_state"]["global_step"] * 32 == samples
            measured += [s["metrics"]["mae"], s["metrics"]["mle"]]
        _agree(_numbers(xavier), measured)


def _sequence_rows(path: Path) -> dict[tuple[str, str, str, str], dict]:
    """eval-sequences' results.csv keyed by (orientation, checkpoint, scale, occlusion)."""
    return {(r["orientation"], r["checkpoint"], r["scale"], r["occlusion"]): r for r in _csv(path)}


def _mae_mre_mle(row: dict) -> list[float]:
    return [float(row[k]) for k in ("mae", "mre", "mle")]


#: Table 5.2's page rows (first cell) and the checkpoint, scale and occlusion flag of their line
#: in its results.csv
TABLE_5_2_ROWS = {
    "constant plane (GT median)": ("", "GT", "False"),
    "supervised DepthNet (P, D + O)": (
        "runs/compare-64/depthnet/checkpoints/best.pt",
        "P",
        "False",
    ),
    "unsupervised DepthNet (P, O, occlusion module off)": (
        "runs/t52/unsup-O/checkpoints/best.pt",
        "P",
        "False",
    ),
    "unsupervised DepthNet (P, O, occlusion module on)": (
        "runs/t52/unsup-O-odm/checkpoints/best.pt",
        "P",
        "True",
    ),
    "unsupervised DepthNet (P, no supervision: 6-DoF PoseNet)": (
        "runs/t52/unsup-6dof/checkpoints/best.pt",
        "P",
        "False",
    ),
    "SFMLearner (P, O)": ("runs/t52/sfm/checkpoints/best.pt", "P", "False"),
    "SFMLearner (GT, O)": ("runs/t52/sfm/checkpoints/best.pt", "GT", "False"),
}


def test_table_5_2_page_matches_its_results_csv():
    folder = RESULTS / "table-5.2"
    scored = _sequence_rows(folder / "results.csv")
    text = (folder / "README.md").read_text()
    rows = {cells[0]: cells for cells in _rows(folder / "README.md", r"[a-zA-Z].*\(.*")}
    assert set(TABLE_5_2_ROWS) <= set(rows)
    for label, (ckpt, scale, occlusion) in TABLE_5_2_ROWS.items():
        _agree(_numbers(rows[label][1]), _mae_mre_mle(scored[("upright", ckpt, scale, occlusion)]))
    # the upside-down paragraph lists every row's MAE in the table's order
    upside = text.split("Upside down (Table 5.3")[1].split("\n\n")[0]
    measured = [float(scored[("upside-down", *key)]["mae"]) for key in TABLE_5_2_ROWS.values()]
    _agree(_numbers(upside.split("the same rows: ")[1].split(" m MAE")[0]), measured)


def test_unsupervised_reference_table_matches_its_results_csv():
    folder = RESULTS / "reference" / "unsupervised"
    scored = _sequence_rows(folder / "outputs" / "results.csv")
    ours, author = "runs/ref-unsup/ours/checkpoints/", "runs/ref-unsup/author/author.pt"
    expected = {
        "constant plane (GT median)": [("", "GT")],
        "ours": [(ours + "best.pt", "P"), (ours + "best.pt", "P (fixed pair)")],
        "author's code": [(author, "P"), (author, "P (fixed pair)")],
    }
    for label, keys in expected.items():
        # the first such row: the 64 px table (the 128 px section's has its own test)
        cells = _rows(folder / "README.md", re.escape(label) + r"( \(.*)?")[0]
        for cell, (ckpt, scale) in zip(cells[1:], keys, strict=False):
            _agree(_numbers(cell), _mae_mre_mle(scored[("upright", ckpt, scale, "False")]))
    last = scored[("upright", ours + "last.pt", "P", "False")]
    assert _mae_mre_mle(last) == _mae_mre_mle(scored[("upright", ours + "best.pt", "P", "False")])


def test_unsupervised_reference_128px_table_matches_its_results_csv():
    """The author's code at 128 px: every epoch's row (both pair rules, PoseNet's cosine) and the
    constant plane, read back from 128px/results.csv."""
    folder = RESULTS / "reference" / "unsupervised"
    scored = _sequence_rows(folder / "128px" / "results.csv")
    section = (folder / "README.md").read_text().split("## At 128 px")[1].split("\n## ")[0]
    table = _table(section)
    constant = scored[("upright", "", "GT", "False")]
    _agree(_numbers(table["constant plane (GT median)"][2]), _mae_mre_mle(constant))
    epochs = [k for k in table if k.startswith("epoch ")]
    assert epochs == [f"epoch {k}" for k in range(1, 11)]
    for label in epochs:
        k = int(label.split()[1])
        cells = table[label]
        assert cells[1] == f"{200 * k:,}"
        ckpt = f"runs/ref-unsup-128/author/epoch{k}.pt"
        rule = scored[("upright", ckpt, "P", "False")]
        _agree(_numbers(cells[2]), _mae_mre_mle(rule))
        _agree(
            _numbers(cells[3]), _mae_mre_mle(scored[("upright", ckpt, "P (fixed pair)", "False")])
        )
        _agree(_numbers(cells[4]), _cosine(rule))


def _table(text: str) -> dict[str, list[str]]:
    """The markdown table rows of ``text`` by first cell (header and rule rows included)."""
    rows = {}
    for line in text.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells
    return rows


def _cosine(row: dict) -> list[float]:
    return [float(row["pose_cosine"])] if row.get("pose_cosine") else []


def test_unsup_128_tables_match_their_outputs():
    folder = RESULTS / "unsup-128"
    text = (folder / "README.md").read_text()
    runs, control = text.split("## Runs and results")[1].split("## The control")
    control, losses = control.split("## Where the training loss")
    control, later = control.split("## The author's code and a faster PoseNet")
    scored = {
        name: _sequence_rows(folder / name / "results.csv")
        for name in (
            *("orientation", "supervised", "finetune", "known-motion"),
            *("known-motion-continued", "finetune-warmup", "finetune-smooth-weight-0"),
        )
    }
    main = {
        "constant plane (GT median)": ("orientation", ""),
        "`depthnet-unsup --pose orientation`, epoch 1": (
            "orientation",
            "unsup-128/kept/epoch_1.pt",
        ),
        "same, epoch 4": ("orientation", "unsup-128/kept/epoch_4.pt"),
        "same, epoch 8 (stopped)": ("orientation", "unsup-128/kept/epoch_8.pt"),
        "supervised `depthnet` (D + O), `best.pt`": ("supervised", "sup-128/O/checkpoints/best.pt"),
        "D + O → O: `depthnet-unsup --pose orientation --pretrained` the supervised `best.pt`, "
        "epoch 1": ("finetune", "ft-128/kept/epoch_1.pt"),
        "same, epoch 3": ("finetune", "ft-128/kept/epoch_3.pt"),
        "D + O → O with `--smooth-weight 0`, epoch 1": (
            "finetune-smooth-weight-0",
            "ft-128-sw0/orientation/kept/epoch_1.pt",
        ),
        "same without smooth term, epoch 3": (
            "finetune-smooth-weight-0",
            "ft-128-sw0/orientation/kept/epoch_3.pt",
        ),
        "D + O → O with `--pose-warmup 200 --smooth-weight 0`, epoch 2 (end of the warm-up: "
        "DepthNet still the supervised one)": (
            "finetune-warmup",
            "ft-128-pw200/orientation/kept/epoch_2.pt",
        ),
        "same warm-up run, epoch 4": (
            "finetune-warmup",
            "ft-128-pw200/orientation/kept/epoch_4.pt",
        ),
    }
    table = _table(runs)
    for label, (name, ckpt) in main.items():
        cells = table[label]
        ckpt = f"runs/{ckpt}" if ckpt else ""
        rule = scored[name][("upright", ckpt, "P" if ckpt else "GT", "False")]
        _agree(_numbers(cells[3]), _mae_mre_mle(rule))
        if ckpt:
            fixed = scored[name][("upright", ckpt, "P (fixed pair)", "False")]
            _agree(_numbers(cells[4]), _mae_mre_mle(fixed))
            _agree(_numbers(cells[5]), _cosine(rule))
    table, known = _table(control), scored["known-motion"]
    constant = known[("upright", "", "GT", "False")]
    _agree(_numbers(table["constant plane (GT median)"][1]), _mae_mre_mle(constant))
    continued = scored["known-motion-continued"]
    rows = [(f"epoch {e} (", f"runs/km-128/kept/epoch_{e}.pt", known) for e in (4, 8, 12)]
    rows += [
        (
            f"continued, epoch {12 + e} (",
            f"runs/km-128-cont/known-motion/kept/epoch_{e}.pt",
            continued,
        )
        for e in (4, 8)
    ]
    for start, ckpt, results in rows:
        (label,) = [k for k in table if k.startswith(start)]
        _agree(_numbers(table[label][1]), _mae_mre_mle(results[("upright", ckpt, "P", "False")]))
        fixed = results[("upright", ckpt, "P (fixed pair)", "False")]
        _agree(_numbers(table[label][2]), _mae_mre_mle(fixed))
    # the loss table: each depth's loss with the true and with PoseNet's translations, as printed
    printed: dict[str, list[float]] = {}
    for line in (folder / "orientation" / "loss_at_candidates.md").read_text().splitlines()[3:]:
        depth, _, _, _, loss = (c.strip() for c in line.strip("|").split("|"))
        printed.setdefault(depth, []).append(float(loss))
    quoted = {k: v for k, v in _table(losses).items() if _numbers(v[1])}
    assert len(quoted) == len(printed) == 8
    for label, cells in quoted.items():
        depth = "the checkpoint's depth" if label == "the checkpoint's own" else label
        _agree(_numbers(" ".join(cells[1:])), printed[depth])


def _training_cosine(steps_csv: Path, after: int, upto: int) -> list[float]:
    """The mean PoseNet cosine of a run's logged training steps after ``after``, to ``upto``."""
    values = [float(r["pose_cosine"]) for r in _csv(steps_csv) if after < int(r["step"]) <= upto]
    return [sum(values) / len(values)]


def test_table_5_2_128_page_matches_its_outputs():
    """Every row of the 128 px Table 5.2: both pair rules and the test cosine from the
    eval-sequences results.csv it names, the training cosine from the run's steps.csv, and each
    new row's seconds."""
    folder = RESULTS / "table-5.2-128"
    unsup = RESULTS / "unsup-128"
    here, runs = folder / "results.csv", "runs/table-5.2-128/"
    rows = {
        "constant plane (GT median)": (here, "", "GT", "False", None),
        "supervised DepthNet (P, D + O)": (
            unsup / "supervised" / "results.csv",
            "runs/sup-128/O/checkpoints/best.pt", "P", "False", None,
        ),
        "unsupervised DepthNet (P, O, occlusion module off)": (
            unsup / "orientation" / "results.csv",
            "runs/unsup-128/kept/epoch_4.pt", "P", "False", None,
        ),
        "unsupervised DepthNet (P, O, off), PoseNet at Adam 1e-3 (`--pose-lr`)": (
            unsup / "orientation-pose-lr" / "results.csv",
            "runs/unsup-128-poselr/orientation/kept/epoch_4.pt", "P", "False",
            unsup / "orientation-pose-lr" / "steps.csv",
        ),
        "unsupervised DepthNet (P, O, occlusion module on)": (
            here, runs + "unsup-O-odm/checkpoints/last.pt", "P", "True",
            folder / "unsup-O-odm" / "steps.csv",
        ),
        "unsupervised DepthNet (P, no supervision: 6-DoF PoseNet)": (
            here, runs + "unsup-6dof/checkpoints/last.pt", "P", "False",
            folder / "unsup-6dof" / "steps.csv",
        ),
        "SFMLearner (P, O)": (
            here, runs + "sfm/checkpoints/last.pt", "P", "False", folder / "sfm" / "steps.csv",
        ),
        "SFMLearner (GT, O)": (
            here, runs + "sfm/checkpoints/last.pt", "GT", "False", folder / "sfm" / "steps.csv",
        ),
    }  # fmt: skip
    text = (folder / "README.md").read_text()
    table = _table(text.split("## Test split")[1].split("\n## ")[0])
    for label, (results, ckpt, scale, occlusion, steps) in rows.items():
        cells, scored = table[label], _sequence_rows(results)
        row = scored[("upright", ckpt, scale, occlusion)]
        _agree(_numbers(cells[2]), _mae_mre_mle(row))
        fixed = scored.get(("upright", ckpt, "P (fixed pair)", occlusion))
        _agree(_numbers(cells[3]), _mae_mre_mle(fixed) if fixed else [])
        test, _, training = cells[4].partition(" / ")
        _agree(_numbers(test), _cosine(row))
        _agree(_numbers(training), _training_cosine(steps, 300, 400) if steps else [])
    quoted = text.split("each\nrun's `seconds.txt` (")[1].split(")")[0]
    seconds = [
        float((folder / n / "seconds.txt").read_text())
        for n in ("unsup-O-odm", "unsup-6dof", "sfm")
    ]
    assert [float(v.replace(",", "")) for v in re.findall(r"[\d,]+(?= s)", quoted)] == seconds


def _percent_of(value: float, constant: float) -> str:
    """``value`` against ``constant`` as the pages print it: "−4.2 %" (better), "+3.1 %"."""
    change = 100 * (value / constant - 1)
    return f"{'−' if change < 0 else '+'}{abs(change):.1f} %"


def _table_5800_section() -> tuple[str, str]:
    """The 5,800-step section of the 128 px Table 5.2 page, as written and on one line."""
    page = RESULTS / "table-5.2-128" / "README.md"
    section = page.read_text().split("## 5,800 steps per row")[1].split("\n## ")[0]
    return section, " ".join(section.split())


def test_table_5_2_128_at_5800_steps_matches_its_outputs():
    """The 5,800-step Table 5.2 at 128 px: the constant and both supervised rows from their runs'
    eval-sequences, the "O" row from the 1,519-scene run's step-5,800 checkpoint (test and
    training cosines), the margins quoted, the stabilised-test comparison, the supervised runs'
    seconds, best epochs and test MAE on their own pairs."""
    folder = RESULTS / "table-5.2-128"
    section, flat = _table_5800_section()
    table = _table(section)
    supervised = _sequence_rows(folder / "5800" / "supervised" / "results.csv")
    best = "runs/sup-128-30/checkpoints/best.pt"
    rotating = _sequence_rows(folder / "5800" / "supervised-rotating" / "results.csv")
    rot_best = "runs/sup-128-rot-30/checkpoints/best.pt"
    o_run = RESULTS / "unsup-128" / "orientation-1900"
    o_ckpt = "runs/unsup-128-1900/orientation/kept/epoch_58.pt"
    o_scored = _sequence_rows(o_run / "results.csv")
    occ_run = folder / "5800" / "occlusion"
    occ_ckpt = "runs/unsup-128-1900/occlusion/kept/epoch_{}.pt".format

    def with_module(path: Path) -> dict:
        """A module-on run's rows (occlusion True but the constant's), keyed as the others'."""
        rows = _sequence_rows(path)
        assert all((k[3] == "True") == bool(k[1]) for k in rows)
        return {(*k[:3], "False"): r for k, r in rows.items()}

    occ_scored = with_module(occ_run / "results.csv")
    _agree(_numbers(table["constant plane (GT median)"][2]),
           _mae_mre_mle(supervised[("upright", "", "GT", "False")]))  # fmt: skip
    rows = {
        "supervised DepthNet (P, D + O)": (supervised, best, None),
        "supervised DepthNet (P, D + O), trained on the rotating scenes": (
            rotating,
            rot_best,
            None,
        ),
        "unsupervised DepthNet (P, O, occlusion module off)": (o_scored, o_ckpt, o_run),
        "unsupervised DepthNet (P, O, occlusion module on)": (occ_scored, occ_ckpt(58), occ_run),
    }
    for label, (scored, ckpt, run) in rows.items():
        cells = table[label]
        rule = scored[("upright", ckpt, "P", "False")]
        _agree(_numbers(cells[2]), _mae_mre_mle(rule))
        _agree(
            _numbers(cells[3]), _mae_mre_mle(scored[("upright", ckpt, "P (fixed pair)", "False")])
        )
        test, _, training = cells[4].partition(" / ")
        _agree(_numbers(test), _cosine(rule))
        _agree(_numbers(training),
               _training_cosine(run / "steps.csv", 5700, 5800) if run else [])  # fmt: skip

    # the rotating-trained row against "O" and the constant, as quoted in bold and below
    def row_mae(scored: dict, ckpt: str, rule: str) -> float:
        return float(scored[("upright", ckpt, rule, "False")]["mae"])

    sup_p, sup_f = (row_mae(rotating, rot_best, r) for r in ("P", "P (fixed pair)"))
    o_p, o_f = (row_mae(o_scored, o_ckpt, r) for r in ("P", "P (fixed pair)"))
    constant = float(supervised[("upright", "", "GT", "False")]["mae"])
    assert (f"{sup_p:.2f} against {o_p:.2f} m under \"P\" and {sup_f:.2f} against {o_f:.2f} m "
            f"with the fixed pair (−{100 * (1 - sup_p / constant):.1f} % and "
            f"−{100 * (1 - sup_f / constant):.1f} %") in flat  # fmt: skip
    assert f'margin over "O" ({o_p - sup_p:.2f} m)' in flat
    assert f"with the fixed pair ({o_f - sup_f:.2f} m) it is not" in flat
    picked = rotating[("upright", rot_best, "P", "False")]["shifts_used"]  # "1:216 2:146 ..."
    one_frame = dict(gap.split(":") for gap in picked.split())["1"]
    assert (
        f"costs this row {sup_p - sup_f:.2f} m: it picks the 1-frame pair on {one_frame} of 416"
        in flat
    )
    # both networks on the stabilised test split, as quoted ("P" / fixed pair), and the constant
    stable = _sequence_rows(folder / "5800" / "stabilised-test" / "results.csv")
    mae = {k: float(r["mae"]) for k, r in stable.items()}
    quoted = flat.split("thesis' for both supervised rows: ")[1].split(" constant")[0]
    _agree(_numbers(quoted), [mae[("upright", best, "P", "False")],
                              mae[("upright", best, "P (fixed pair)", "False")],
                              mae[("upright", o_ckpt, "P", "False")],
                              mae[("upright", o_ckpt, "P (fixed pair)", "False")]])  # fmt: skip
    assert f"constant {mae[('upright', '', 'GT', 'False')]:.2f} m" in flat
    stable_rot = _sequence_rows(
        folder / "5800" / "supervised-rotating" / "stabilised-test" / "results.csv"
    )
    quoted = flat.split("the rotating-trained supervised row ")[1].split(" m")[0]
    _agree(_numbers(quoted), [row_mae(stable_rot, rot_best, r) for r in ("P", "P (fixed pair)")])
    # the occlusion row against "O", its curve every 400 steps, on 177 scenes, and its seconds
    occ_p, occ_f = (row_mae(occ_scored, occ_ckpt(58), r) for r in ("P", "P (fixed pair)"))
    assert (f"scores {occ_p:.2f} / {occ_f:.2f} m** (\"P\" / fixed pair, "
            f"{_percent_of(occ_p, constant)} / {_percent_of(occ_f, constant)}), "
            f"{occ_p - o_p:.2f} m behind") in flat  # fmt: skip
    curve = {16: "{} m at 1,600 steps", 40: "from 4,000 steps ({} m)", 48: "{} m at 4,800",
             56: "{} m at 5,600"}  # fmt: skip
    for epoch, quoted in curve.items():
        assert quoted.format(f"{row_mae(occ_scored, occ_ckpt(epoch), 'P'):.2f}") in flat
    first_below = min(k for k in range(8, 59, 4) if ("upright", occ_ckpt(k), "P", "False") in
                      occ_scored and row_mae(occ_scored, occ_ckpt(k), "P") < constant)  # fmt: skip
    assert first_below == 40
    cosine = float(occ_scored[("upright", occ_ckpt(16), "P", "False")]["pose_cosine"])
    assert f"test cosine {cosine:.2f})" in flat
    wide_occ = with_module(occ_run / "test-177" / "results.csv")
    quoted = flat.split("On the 177 test scenes: ")[1].split(" m")[0]
    _agree(_numbers(quoted), [row_mae(wide_occ, occ_ckpt(58), r) for r in ("P", "P (fixed pair)")])
    epochs = _csv(occ_run / "metrics.csv")
    assert len(epochs) == 58 and int(epochs[-1]["step"]) == 5800
    seconds = [float(r["seconds"]) for r in epochs]
    assert f"Training took {sum(seconds):,.0f} s" in flat
    assert f"median epoch {statistics.median(seconds):.0f} s" in flat
    # the same two rows on all 177 test scenes of the 1,900-scene set, as quoted
    wide = _sequence_rows(folder / "5800" / "test-177" / "results.csv")
    wide_mae = {k: float(r["mae"]) for k, r in wide.items()}
    maes = [wide_mae[("upright", c, r, "False")] for c in (rot_best, o_ckpt)
            for r in ("P", "P (fixed pair)")]  # fmt: skip
    wide_constant = wide_mae[("upright", "", "GT", "False")]
    quoted = _numbers(flat.split("supervised (rotating) ")[1].split(" The margins")[0])
    _agree(quoted[:5], [*maes, wide_constant])
    assert quoted[5:] == [round(100 * (m / wide_constant - 1), 1) for m in maes]
    assert f"margins are {maes[2] - maes[0]:.2f} and {maes[3] - maes[1]:.2f} m" in flat
    assert f"({int(wide[('upright', '', 'GT', 'False')]['sequences']):,} sequences" in flat
    # the supervised run: 30 epochs, the best validation at the last, its seconds and test MAE
    epochs = _csv(folder / "5800" / "supervised" / "metrics.csv")
    assert len(epochs) == 30 and min(epochs, key=lambda r: float(r["val_mae"])) is epochs[-1]
    assert (
        int(epochs[-1]["step"]) == 4530
        and "4,530 steps of 32" in table["supervised DepthNet (P, D + O)"][1]
    )
    seconds = sum(float(r["seconds"]) for r in epochs)
    assert f"training took {seconds:,.0f} s" in flat
    own = json.loads((folder / "5800" / "supervised" / "summary.json").read_text())
    before = json.loads((RESULTS / "unsup-128" / "supervised-again" / "summary.json").read_text())
    assert (f"(`summary.json`) is {own['metrics']['mae']:.2f} m, against "
            f"{before['metrics']['mae']:.2f} m") in flat  # fmt: skip
    # the rotating-trained run: 30 epochs of 151 steps, the best validation at the quoted epoch
    epochs = _csv(folder / "5800" / "supervised-rotating" / "metrics.csv")
    best_epoch = min(epochs, key=lambda r: float(r["val_mae"]))
    assert len(epochs) == 30 and int(epochs[-1]["step"]) == 4530
    label = "supervised DepthNet (P, D + O), trained on the rotating scenes"
    assert (f"{int(best_epoch['step']):,} steps of 32 on 1,519 rotating scenes (`best.pt`, "
            f"epoch {int(float(best_epoch['epoch']))} of 30)") in table[label][1]  # fmt: skip
    seconds = sum(float(r["seconds"]) for r in epochs)
    assert f"rotating-trained run took {seconds:,.0f} s" in flat
    own = json.loads((folder / "5800" / "supervised-rotating" / "summary.json").read_text())
    assert own["training_state"]["global_step"] == int(best_epoch["step"])
    report = (folder / "5800" / "supervised-rotating" / "summary.md").read_text()
    pairs = int(report.split("Split `test`: ")[1].split(" pairs")[0])
    assert (f"({pairs:,} of {own['scenes']} scenes) it scores "
            f"{own['metrics']['mae']:.2f} m") in flat  # fmt: skip


def _o_row_1900(epoch: int) -> dict:
    """The "O" row's eval-sequences line ("P") of the 1,519-scene run's checkpoint ``epoch``."""
    rows = _sequence_rows(RESULTS / "unsup-128" / "orientation-1900" / "results.csv")
    return rows[("upright", f"runs/unsup-128-1900/orientation/kept/epoch_{epoch}.pt", "P", "False")]


def test_table_5_2_128_6dof_row_matches_its_outputs():
    """The 6-DoF row of the 5,800-step Table 5.2 at 128 px, trained for one session's budget:
    its cells from the last scored checkpoint, its budget from metrics.csv, the curve every 400
    steps, the "O" row at the same steps, the 177-scene pair, seconds and median epoch."""
    folder = RESULTS / "table-5.2-128"
    section, flat = _table_5800_section()
    cells = _table(section)["unsupervised DepthNet (P, no supervision: 6-DoF PoseNet)"]
    run = folder / "5800" / "6dof"
    epochs = _csv(run / "metrics.csv")
    last, steps = len(epochs), int(epochs[-1]["step"])
    assert steps == 100 * last and f"{steps:,} steps of 16" in cells[1]
    ckpt = "runs/unsup-128-1900/6dof/kept/epoch_{}.pt".format
    scored = _sequence_rows(run / "results.csv")

    def mae(epoch: int, rule: str = "P", rows: dict = scored) -> float:
        return float(rows[("upright", ckpt(epoch), rule, "False")]["mae"])

    rule = scored[("upright", ckpt(last), "P", "False")]
    _agree(_numbers(cells[2]), _mae_mre_mle(rule))
    fixed = scored[("upright", ckpt(last), "P (fixed pair)", "False")]
    _agree(_numbers(cells[3]), _mae_mre_mle(fixed))
    test, _, training = cells[4].partition(" / ")
    _agree(_numbers(test), _cosine(rule))
    _agree(_numbers(training), _training_cosine(run / "steps.csv", steps - 100, steps))
    constant = float(scored[("upright", "", "GT", "False")]["mae"])
    p, f = mae(last), mae(last, "P (fixed pair)")
    assert (f"scores {p:.2f} / {f:.2f} m after {steps:,} steps** (\"P\" / fixed pair, "
            f"{_percent_of(p, constant)} / {_percent_of(f, constant)}") in flat  # fmt: skip
    # the curve under "P" every 400 steps from 800, and the "O" row at 800 and at the last step
    curve = flat.split("every 400 steps from 800: ")[1].split(" m")[0]
    every = list(range(8, last + 1, 4))
    assert every[-1] == last
    _agree(_numbers(curve), [mae(k) for k in every])
    quoted = flat.split("test cosine rises meanwhile (every 400 steps from 800: ")[1]
    _agree(_numbers(quoted.split(")")[0]), [_cosine(scored[("upright", ckpt(k), "P", "False")])[0]
                                             for k in every])  # fmt: skip
    gaps = [mae(k) - constant for k in every]
    assert f"the depth stays {min(gaps):.1f}-{max(gaps):.1f} m above the constant" in flat
    o_at = [float(_o_row_1900(k)["mae"]) for k in (8, last)]
    assert (f'the "O" row was at {o_at[0]:.2f} m at 800 steps and {o_at[1]:.2f} m at '
            f"{steps:,}") in flat  # fmt: skip
    wide = _sequence_rows(run / "test-177" / "results.csv")
    quoted = flat.split("6-DoF row on the 177 test scenes: ")[1].split(" m")[0]
    _agree(_numbers(quoted), [mae(last, r, wide) for r in ("P", "P (fixed pair)")])
    seconds = [float(r["seconds"]) for r in epochs]
    assert (f"It trained in {sum(seconds):,.0f} s (`metrics.csv`; median epoch "
            f"{statistics.median(seconds):.0f} s on two threads") in flat  # fmt: skip


def test_table_5_2_128_sfmlearner_rows_match_their_outputs():
    """The SFMLearner rows of the 5,800-step Table 5.2 at 128 px (scaled by its PoseNet and by
    the ground truth's median), trained for one session's budget: their cells from the last
    scored checkpoint, the budget from metrics.csv, the curves every 400 steps, the 177-scene
    pair, seconds and median epoch."""
    folder = RESULTS / "table-5.2-128"
    section, flat = _table_5800_section()
    table = _table(section)
    run = folder / "5800" / "sfmlearner"
    epochs = _csv(run / "metrics.csv")
    last, steps = len(epochs), int(epochs[-1]["step"])
    ckpt = "runs/unsup-128-1900/sfmlearner/kept/epoch_{}.pt".format
    scored = _sequence_rows(run / "results.csv")

    def row(epoch: int, scale: str, rows: dict = scored) -> dict:
        return rows[("upright", ckpt(epoch), scale, "False")]

    assert steps == 100 * last
    training = _training_cosine(run / "steps.csv", steps - 100, steps)
    assert f"{steps:,} steps of 16" in table["SFMLearner (P, O)"][1]
    for name, scale in (("SFMLearner (P, O)", "P"), ("SFMLearner (GT, O)", "GT")):
        cells = table[name]
        assert cells[3] == "–"
        _agree(_numbers(cells[2]), _mae_mre_mle(row(last, scale)))
        test, _, on_training = cells[4].partition(" / ")
        _agree(_numbers(test), _cosine(row(last, scale)))
        _agree(_numbers(on_training), training)
    constant = float(scored[("upright", "", "GT", "False")]["mae"])
    p, g = (float(row(last, scale)["mae"]) for scale in ("P", "GT"))
    assert (f"scores {p:.2f} m scaled by its PoseNet and {g:.2f} m by the ground truth's median "
            f"after {steps:,} steps** ({_percent_of(p, constant)} / {_percent_of(g, constant)}"
            ) in flat  # fmt: skip
    every = list(range(4, last + 1, 4))
    assert every[-1] == last
    for label, scale in (("scaled by its PoseNet", "P"), ("by the ground truth's median", "GT")):
        curve = flat.split(f"every 400 steps from 400, {label}: ")[1].split(" m")[0]
        _agree(_numbers(curve), [float(row(k, scale)["mae"]) for k in every])
    gap = max(abs(float(row(k, "GT")["mae"]) - constant) for k in every)
    assert f"within {gap:.1f} m of the constant plane" in flat
    first = row(every[0], "P")
    assert (f"at {every[0] * 100} steps, divided by too short a translation, its maps are far "
            f"too far: MRE {float(first['mre']):.2f}") in flat  # fmt: skip
    quoted = flat.split("PoseNet's test cosine (every 400 steps from 400: ")[1].split(";")[0]
    _agree(_numbers(quoted), [_cosine(row(k, "P"))[0] for k in every])
    o_20, o_24 = _o_row_1900(20), _o_row_1900(24)
    c_20, c_24 = (f"{_cosine(r)[0]:.2f}".replace("-", "−") for r in (o_20, o_24))
    assert f'the "O" row\'s was {c_20} at 2,000 steps and {c_24} at 2,400' in flat
    assert (f"the \"O\" row's {float(o_20['mae']):.2f} and {float(o_24['mae']):.2f} m at 2,000 "
            "and 2,400 steps") in flat  # fmt: skip
    wide = _sequence_rows(run / "test-177" / "results.csv")
    quoted = flat.split("SFMLearner rows on the 177 test scenes: ")[1].split(" m")[0]
    _agree(_numbers(quoted), [float(row(last, s, wide)["mae"]) for s in ("P", "GT")])
    seconds = [float(r["seconds"]) for r in epochs]
    assert (f"SFMLearner trained in {sum(seconds):,.0f} s (`metrics.csv`; median epoch "
            f"{statistics.median(seconds):.0f} s on two threads") in flat  # fmt: skip


def _check_unsup_128_checkpoints(section: str, runs: dict[str, tuple[str, str]]) -> int:
    """Every "[prefix]N steps" row of ``section``'s tables against its run (``runs``: row prefix →
    (folder here, run.sh's runs folder)): both pair rules and the test cosine from the run's
    merged results.csv, the ratio to the constant, the training cosine of the last 100 steps from
    steps.csv and the validation MAE from metrics.csv. Returns the number of rows checked."""
    folder = RESULTS / "unsup-128"
    table = _table(section)
    named = "|".join(re.escape(p) for p in runs if p)
    labels = [k for k in table if re.fullmatch(rf"({named})?[\d,]+ steps", k)]
    for label in labels:
        prefix = next((p for p in runs if p and label.startswith(p)), "")
        run = folder / runs[prefix][0]
        scored = _sequence_rows(run / "results.csv")
        constant = float(scored[("upright", "", "GT", "False")]["mae"])
        validation = {int(r["step"]): float(r["val_mae"]) for r in _csv(run / "metrics.csv")}
        steps = int(label.removeprefix(prefix).split()[0].replace(",", ""))
        ckpt = f"runs/{runs[prefix][1]}/orientation/kept/epoch_{steps // 100}.pt"
        cells = table[label]
        rule = scored[("upright", ckpt, "P", "False")]
        fixed = scored[("upright", ckpt, "P (fixed pair)", "False")]
        _agree(_numbers(cells[1]), _mae_mre_mle(rule))
        _agree(_numbers(cells[2]), _mae_mre_mle(fixed))
        ratios = cells[3].replace("\u2212", "-").replace(" %", "").split(" / ")
        assert ratios == [f"{100 * (float(r['mae']) / constant - 1):+.1f}" for r in (rule, fixed)]
        test, _, training = cells[4].partition(" / ")
        _agree(_numbers(test), _cosine(rule))
        _agree(_numbers(training), _training_cosine(run / "steps.csv", steps - 100, steps))
        _agree(_numbers(cells[5]), [validation[steps]])
    return len(labels)


def test_unsup_128_pose_lr_table_matches_its_outputs():
    """The --pose-lr, recipe and D + O → O runs' checkpoints (`_check_unsup_128_checkpoints`),
    the D + O → O run's supervised start, and the pose-generalisation table from its three
    outputs."""
    folder = RESULTS / "unsup-128"
    section = (folder / "README.md").read_text().split("## The author's code and a faster")[1]
    section = section.split("\n## ")[0]
    runs = {
        "": ("orientation-pose-lr", "unsup-128-poselr"),
        "recipe, ": ("orientation-recipe", "unsup-128-recipe"),
        "D + O → O, ": ("finetune-warmup-1000", "ft-128-warm1000"),
    }
    assert _check_unsup_128_checkpoints(section, runs) == 20
    # the D + O -> O run's supervised start: its test MAE on stabilised pairs and its best step
    again = json.loads((folder / "supervised-again" / "summary.json").read_text())
    quoted = section.split("test MAE on its stabilised test pairs ")[1].split(" m")[0]
    assert float(quoted) == round(again["metrics"]["mae"], 2)
    best = min(_csv(folder / "supervised-again" / "metrics.csv"), key=lambda r: float(r["val_mae"]))
    assert "best of 8 epochs at 906 steps" in section and best["step"] == "906"
    # pose_generalisation.py: the training cosines at 100, 300, 400, 600 steps and the test range
    outputs = {
        ("the rotating frames", "2e-4 (the recipe's)"): "rotating-lr2e-4.txt",
        ("the rotating frames", "1e-3"): "rotating-lr1e-3.txt",
        ("frames stabilised to the last one", "2e-4"): "stabilised-lr2e-4.txt",
    }
    rows = [line for line in section.splitlines() if line.startswith("| the rotating") or
            line.startswith("| frames stabilised")]  # fmt: skip
    assert len(rows) == len(outputs)
    for line in rows:
        reads, lr, training, test = (c.strip() for c in line.strip("|").split("|"))
        text = (folder / "pose-generalisation" / outputs[(reads, lr)]).read_text()
        train = {
            int(s): float(c)
            for s, c in re.findall(r"after (\d+) steps: training cosine (-?[\d.]+)", text)
        }
        tests = [
            float(c)
            for c in re.findall(r"\d+ steps: training cosine .*test cosine (-?[\d.]+)", text)
        ]
        _agree(_numbers(training), [train[k] for k in (100, 300, 400, 600)])
        _agree(_numbers(test), [min(tests), max(tests)])


def test_unsup_128_more_scenes_table_matches_its_outputs():
    """The recipe on 1,519 training scenes and its continuation at lr 6e-5: their checkpoints
    (`_check_unsup_128_checkpoints`), the continuation's settings and seconds, the
    training-cosine range, the late test cosines, the seconds of training and validation (in all,
    and the median epoch's) and the ratios quoted; and PoseNet's cosines against the true depth on
    those scenes (pose_generalisation.py's output)."""
    folder = RESULTS / "unsup-128"
    section = (folder / "README.md").read_text().split("## More training scenes")[1]
    section = section.split("\n## ")[0]
    flat = " ".join(section.split())  # the page's text without its line breaks
    runs = {
        "1,519 scenes, ": ("orientation-1900", "unsup-128-1900"),
        "lr 6e-5 from 5,800, ": ("orientation-1900-lr", "unsup-128-1900-lr"),
    }
    assert _check_unsup_128_checkpoints(section, runs) == 27
    lowered = json.loads((folder / "orientation-1900-lr" / "config.json").read_text())
    assert (lowered["lr"], lowered["pretrained"]) == (
        6e-5,
        "runs/unsup-128-1900/orientation/kept/epoch_58.pt",
    )
    seconds = sum(float(r["seconds"]) for r in _csv(folder / "orientation-1900-lr" / "metrics.csv"))
    assert f"{seconds:,.0f} s) did not get nearer" in flat
    run = folder / "orientation-1900"
    assert json.loads((run / "config.json").read_text())["data"] == "data/stillbox-rot-128-1900"
    # the budget: the first 58 epochs (5,800 steps); the third continuation's are past it
    epochs = [float(r["seconds"]) for r in _csv(run / "metrics.csv")][:58]
    median = statistics.median(epochs[24:])  # the second continuation's epochs
    assert f"{len(epochs)} epochs at the median epoch's {median:.0f} s are" in flat
    assert f"are {len(epochs) * median:,.0f} s" in flat
    scored = _sequence_rows(run / "results.csv")
    late = [_cosine(scored[("upright", f"runs/unsup-128-1900/orientation/kept/epoch_{k}.pt",
                            "P", "False")])[0] for k in (44, 48, 52, 56, 58)]  # fmt: skip
    assert f"test cosine to {min(late):.2f}-{max(late):.2f} from 4,400 steps on" in flat
    per_100 = [_training_cosine(run / "steps.csv", k, k + 100)[0] for k in range(0, 1900, 100)]
    quoted = section.split("training-batch cosine stayed between ")[1].split(" per 100")[0]
    _agree(_numbers(quoted.replace(" and ", " ")), [min(per_100), max(per_100)])
    assert f"took {sum(epochs):,.0f} s of training and validation" in flat
    scored = _sequence_rows(run / "results.csv")
    constant = float(scored[("upright", "", "GT", "False")]["mae"])
    last = "runs/unsup-128-1900/orientation/kept/epoch_20.pt"
    ratios = [float(scored[("upright", last, rule, "False")]["mae"]) / constant
              for rule in ("P (fixed pair)", "P")]  # fmt: skip
    page = (folder / "README.md").read_text()
    assert f"{ratios[0]:.1f}-{ratios[1]:.1f} times the constant's error" in page
    _check_past_the_budget(flat, run)
    # validation scored again with stabilised references, and unstabilised as logged
    val = {n: json.loads((run / "validation" / f"{n}.json").read_text())["metrics"]["mae"]
           for n in ("stabilised-epoch_32", "stabilised-epoch_58", "stabilised-epoch_80",
                     "unstabilised-epoch_58")}  # fmt: skip
    assert (f"{val['stabilised-epoch_32']:.2f} m at 3,200 steps, "
            f"{val['stabilised-epoch_58']:.2f} m at 5,800 and {val['stabilised-epoch_80']:.2f} m "
            f"at 8,000, where the unstabilised pairs give {val['unstabilised-epoch_58']:.2f} m "
            "at 5,800 (the logged value") in flat  # fmt: skip
    logged = {int(r["step"]): float(r["val_mae"]) for r in _csv(run / "metrics.csv")}
    assert round(logged[5800], 2) == round(val["unstabilised-epoch_58"], 2)
    # PoseNet against the true depth on those scenes: both cosines at each step of the table
    text = (folder / "pose-generalisation" / "rotating-1519-scenes-2000-steps.txt").read_text()
    found = re.findall(
        r"after (\d+) steps: training cosine (-?[\d.]+), test cosine (-?[\d.]+)", text
    )
    cosines = {int(k): (float(a), float(b)) for k, a, b in found}
    table = _table(section)
    steps = [int(c.replace(",", "")) for c in table["steps"][1:]]
    _agree(_numbers("|".join(table["training cosine, last 200 steps"][1:])),
           [cosines[k][0] for k in steps])  # fmt: skip
    _agree(_numbers("|".join(table["test cosine (64 windows of unseen scenes)"][1:])),
           [cosines[k][1] for k in steps])  # fmt: skip


def _check_past_the_budget(flat: str, run: Path) -> None:
    """The continuation of the 1,519-scene run to 8,000 steps, as the page sums it up: its
    seconds and median epoch, and over the checkpoints from 5,200 steps on, each rule's range,
    mean, share past −25 %, the slope of a straight line through them and the spread about it."""
    epochs = [float(r["seconds"]) for r in _csv(run / "metrics.csv")][58:]
    assert f"{sum(epochs):,.0f} s of training and validation, median epoch " in flat
    assert f"median epoch {statistics.median(epochs):.0f} s on one thread" in flat
    scored = _sequence_rows(run / "results.csv")
    constant = float(scored[("upright", "", "GT", "False")]["mae"])
    late = [k for k in range(52, 81) if ("upright", f"runs/unsup-128-1900/orientation/kept/"
            f"epoch_{k}.pt", "P", "False") in scored]  # fmt: skip
    assert f"Over the {len(late)} checkpoints scored from 5,200 to 8,000 steps" in flat
    slopes = []
    for rule, quote in (("P", 'under "P" ranges from '), ("P (fixed pair)", "fixed pair from ")):
        mae = [float(scored[("upright", f"runs/unsup-128-1900/orientation/kept/epoch_{k}.pt",
                             rule, "False")]["mae"]) for k in late]  # fmt: skip
        quoted = flat.split(quote)[1].split(";")[0].replace("\u2212", "-")
        shown = f"{min(mae):.2f} to {max(mae):.2f} m (mean {statistics.mean(mae):.2f} m, "
        assert quoted.startswith(shown + f"{100 * (statistics.mean(mae) / constant - 1):.1f} %")
        past = [k for k, v in zip(late, mae, strict=True) if v <= 0.75 * constant]
        if rule == "P":
            named = [f"{k * 100:,}" for k in past]
            assert f"past −25 % at {', '.join(named[:-1])} and {named[-1]} steps" in flat
            between = sum(0.75 * constant < v <= 0.8 * constant for v in mae)
            short = sum(v > 0.8 * constant for v in mae)
            assert (f"of the {len(late)} checkpoints, {between} are between −20 and −25 % under "
                    f'"P", {len(past)} past −25 % and {short} short of −20 %') in flat  # fmt: skip
        else:
            assert f"past −25 % at {len(past)} of them" in flat
        fit = numpy.polyfit([k * 100 for k in late], mae, 1)
        slopes.append(fit[0] * 1000)
        spread = numpy.std(mae - numpy.polyval(fit, [k * 100 for k in late]))
        assert 0.5 <= spread <= 0.7
    assert f"rises by {slopes[0]:.2f} m" in flat and f"and {slopes[1]:.2f} m (fixed pair)" in flat


def test_longest_scaling_run_matches_its_summary():
    """The longest run's row on the scaling page is its committed summary.json."""
    page = (RESULTS / "scaling" / "README.md").read_text()
    section = page.split("## The longest run")[1]
    row = next(line for line in section.splitlines() if line.startswith("| 1,321,760 |"))
    s = json.loads((RESULTS / "scaling" / "outputs" / "ours-full55-s0-t2.summary.json").read_text())
    assert s["training_state"]["global_step"] * 32 == 1_321_760
    m = s["metrics"]
    cells = row.strip("|").split("|")
    _agree(_numbers("|".join(cells[1:5])), [m["mae"], m["mre"], m["mle"], m["p1.25"]])
    assert float(cells[5]) == round(m["mae"] / 21.85, 2)
    fits = json.loads((RESULTS / "scaling" / "fit.json").read_text())["fits"].values()
    predicted = [
        f["floor"] + math.exp(f["intercept"] + f["slope"] * math.log(1_321_760)) for f in fits
    ]
    _agree(_numbers(cells[6]), predicted)


def test_longest_scaling_runs_depth_bands_match_its_summary():
    """The longest run's error by ground-truth depth on the scaling page is its summary.json's."""
    page = (RESULTS / "scaling" / "README.md").read_text()
    section = page.split("## The longest run")[1]
    rows = [line for line in section.splitlines() if line.startswith("| [") and " m" not in line]
    s = json.loads((RESULTS / "scaling" / "outputs" / "ours-full55-s0-t2.summary.json").read_text())
    bands = s["error_by_depth"]
    assert len(rows) == len(bands) == 4
    for row, band in zip(rows, bands, strict=True):
        cells = row.strip("|").split("|")
        assert cells[0].strip() == f"[{band['from_m']:g}, {band['to_m']:g})"
        assert int(cells[1].replace(",", "")) == band["pixels"]
        _agree(_numbers("|".join(cells[2:])), [band["mae"], band["mre"], band["mle"]])


def test_amp_page_matches_its_outputs():
    """The bf16 page's MAE table is its runs' summaries; its speed ratios are its CSVs'."""
    page = (RESULTS / "amp" / "README.md").read_text()
    out = RESULTS / "amp" / "outputs"
    for seed in (0, 1):
        row = next(line for line in page.splitlines() if line.startswith(f"| {seed} | "))
        cells = row.strip("|").split("|")
        for cell, mode in zip(cells[1:], ("fp32", "bf16"), strict=True):
            s = json.loads((out / f"{mode}-s{seed}.summary.json").read_text())
            config = json.loads((out / f"{mode}-s{seed}.config.json").read_text())
            assert config["amp"] is (mode == "bf16") and s["training_state"]["global_step"] == 3078
            m = s["metrics"]
            _agree(_numbers(cell), [m["mae"], m["mre"], m["mle"]])
    for run in (1, 2):
        rows = _csv(out / f"train-speed-{run}.csv")
        ms = {(int(r["batch"]), r["levers"]): float(r["ms_per_step"]) for r in rows}
        for batch in (8, 32, 256):
            if (batch, "bf16") not in ms:
                continue
            line = next(ln for ln in page.splitlines() if ln.startswith(f"| {batch} | "))
            cells = line.strip("|").split("|")
            assert float(cells[run].strip(" –×") or "nan") == round(
                ms[batch, "on"] / ms[batch, "bf16"], 2
            ), (batch, run)
            assert float(cells[2 + run].strip(" –×")) == round(
                ms[batch, "off"] / ms[batch, "bf16"], 2
            ), (batch, run)


def _section(page: Path, heading: str) -> str:
    """The text of ``page`` from the line ``heading`` to the next heading of its level."""
    text = page.read_text()
    start = text.index(f"\n{heading}\n")
    level = heading.split(" ")[0] + " "
    end = text.find(f"\n{level}", start + len(heading) + 2)
    return text[start : end if end > 0 else len(text)]


def _ours_and_thesis(cell: str) -> tuple[list[float], list[float]]:
    """A cell "ours (thesis)": the numbers before the parenthesis and those inside it."""
    ours, _, thesis = cell.replace("*", "").partition("(")
    numbers = re.compile(r"-?\d+(?:\.\d+)?")
    return [float(v) for v in numbers.findall(ours)], [float(v) for v in numbers.findall(thesis)]


def test_toy_study_page_matches_its_results_json_and_the_thesis():
    """The toy study's summary table (docs/results/toy/README.md, "The full study on these
    scenes") against full/results.json (each loss's optimum, ODM off and on) and Table 4.1
    (benchmark.core.thesis); the starting errors within 10 % of the thesis' fit."""
    from benchmark.core.thesis import TABLE_4_1, TABLE_4_1_KEYS

    page = RESULTS / "toy" / "README.md"
    results = json.loads((RESULTS / "toy" / "full" / "results.json").read_text())
    assert results["le0"]["horizon"] == pytest.approx(1.22, rel=0.1)
    assert results["le0"]["flower"] == pytest.approx(0.57, rel=0.1)
    assert results["iterations"] == 10_000 and len(results["lambdas"]) == 10
    section = _section(page, "## The full study on these scenes")
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0].replace(" ", "_") in TABLE_4_1:
            rows[cells[0].replace(" ", "_")] = cells[1:]
    assert sorted(rows) == sorted(TABLE_4_1)
    for loss, cells in rows.items():
        best = [results["runs"][f"{loss}/odm-{s}"]["best"] for s in ("off", "on")]
        thesis = [dict(zip(TABLE_4_1_KEYS, row, strict=True)) for row in TABLE_4_1[loss]]
        for i, (key, odm) in enumerate([("m", 0), ("m", 1), ("delta_m", 0), ("delta_m", 1)]):
            ours, quoted = _ours_and_thesis(cells[i])
            _agree(ours, [best[odm][key]])
            assert quoted == [thesis[odm][key]]
        for i, (b, th) in enumerate(zip(best, thesis, strict=True)):
            ours, quoted = _ours_and_thesis(cells[4 + i])
            assert ours == [b["lambda"], b["kappa"]] and quoted == [th["lambda"], th["kappa"]]
            ours, quoted = _ours_and_thesis(cells[6 + i])
            _agree(ours, [b["le"]["horizon"], b["le"]["flower"]])
            assert quoted == [th["horizon"], th["flower"]]


def test_unsup_128_what_holds_the_o_row_matches_its_outputs():
    """The "O" row's checkpoints on 177 test scenes, on 100 training against 100 test scenes, and
    the training loss at the step-5,800 checkpoint: every number quoted from its output."""
    folder = RESULTS / "unsup-128"
    section = (folder / "README.md").read_text().split("### What holds the")[1].split("\n#")[0]
    flat = " ".join(section.split())
    run = folder / "orientation-1900"
    ckpt = "runs/unsup-128-1900/orientation/kept/epoch_{}.pt".format

    def mae(path: Path, key: tuple[str, str, str, str]) -> float:
        return float(_sequence_rows(path)[key]["mae"])

    def change(path: Path, epoch: int, rule: str) -> float:
        """Percent change of the MAE of ``epoch``'s checkpoint against the constant plane."""
        constant = mae(path, ("upright", "", "GT", "False"))
        return 100 * (mae(path, ("upright", ckpt(epoch), rule, "False")) / constant - 1)

    rules = ("P", "P (fixed pair)")
    wide = RESULTS / "table-5.2-128" / "5800" / "test-177" / "results.csv"
    wide_o = run / "test-177" / "results.csv"
    narrow = run / "results.csv"
    assert f"constant of {mae(wide, ('upright', '', 'GT', 'False')):.2f} m" in flat
    quoted = flat.split("19.69 m: ")[1].split(" So on a test set")[0]
    changes = [change(wide, 58, "P"), *(change(narrow, 58, r) for r in rules),
               change(wide_o, 64, "P"), *(change(narrow, 64, r) for r in rules),
               *(change(wide_o, 80, r) for r in rules),
               *(change(narrow, 80, r) for r in rules)]  # fmt: skip
    assert _numbers(quoted) == [round(c, 1) for c in changes]
    assert abs(change(wide, 58, "P") - change(wide, 58, "P (fixed pair)")) < 0.05  # "alike"
    assert abs(change(wide_o, 64, "P") - change(wide_o, 64, "P (fixed pair)")) < 0.05
    # DepthNet on 100 training and 100 test scenes; PoseNet's cosine and share above 0.9 there
    split = {
        name: run / "train-and-test-scenes" / f"{name}-100" / "results.csv"
        for name in ("train", "test")
    }
    quoted = _numbers(flat.split("checkpoint scores ")[1].split(": the depth")[0])
    for name, (pct, net, constant) in zip(split, (quoted[:3], quoted[3:]), strict=True):
        assert pct == round(change(split[name], 58, "P"), 1)
        _agree([net, constant], [mae(split[name], ("upright", ckpt(58), "P", "False")),
                                 mae(split[name], ("upright", "", "GT", "False"))])  # fmt: skip
    rows = [_sequence_rows(path)[("upright", ckpt(58), "P", "False")] for path in split.values()]
    quoted = flat.split("its cosine is ")[1].split(" above 0.9")[0]
    assert _numbers(quoted) == [round(float(r["pose_cosine"]), 2) for r in rows]
    assert [int(v) for v in re.findall(r"(\d+) %", quoted)] == [
        round(100 * float(r["pose_cosine_gt_0.9"])) for r in rows
    ]
    # the training loss at candidates, with the true motion and with the run's PoseNet
    losses = {}
    for line in (run / "loss_at_candidates-5800.md").read_text().splitlines()[3:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        losses[cells[0], cells[1]] = float(cells[4])
    quoted = flat.split("the truth's loss is ")[1].split(" Where PoseNet")[0]
    _agree(_numbers(quoted), [losses["truth", "true"], losses["the checkpoint's depth", "true"],
                              losses["the checkpoint's depth", "PoseNet's"],
                              losses["truth", "PoseNet's"]])  # fmt: skip
    better = 100 * (1 - losses["truth", "true"] / losses["the checkpoint's depth", "true"])
    worse = 100 * (losses["truth", "PoseNet's"] / losses["the checkpoint's depth", "PoseNet's"] - 1)
    assert round(better, -1) == 10 and round(worse) == 2 and "about 10 % better" in flat

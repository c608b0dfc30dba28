"""Dataset integrity and path safety (issue 12): file checksums in the records, the integrity
checks of ``validate``, and readers that never open or write a file outside the dataset folder.

Each test corrupts a copy of the session's tiny rendered dataset. "Never opened" is tested with a
FIFO outside the dataset: opening it for reading would block, so a reader that opened it would
hit the subprocess timeout instead of printing its one-line error.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import pytest
from conftest import assert_user_error, run_cli

from stillbox_gen import formats, layout, manifest

TIMEOUT = 120  # seconds; far more than any command here needs unless it blocks on the FIFO


@pytest.fixture
def ds(default_dataset: Path, tmp_path: Path) -> Path:
    """A private copy of the 4-scene default dataset, two levels below ``tmp_path``."""
    out = tmp_path / "a" / "ds"
    shutil.copytree(default_dataset, out)
    return out


def _outside_fifo(tmp_path: Path) -> Path:
    """A FIFO outside the dataset: any open() of it for reading blocks (no writer)."""
    fifo = tmp_path / "outside" / "secret.png"
    fifo.parent.mkdir()
    os.mkfifo(fifo)
    return fifo


def _edit_json(path: Path, change: Callable[[dict], None]) -> None:
    obj = json.loads(path.read_text())
    change(obj)
    path.write_text(json.dumps(obj))


def _edit_record(root: Path, index: int, change: Callable[[dict], None]) -> None:
    """Change scene ``index`` alike in its .records file and in metadata.json."""
    _edit_json(layout.record_path(root, index), change)
    meta = root / layout.chunk_name(index) / "metadata.json"
    _edit_json(meta, lambda m: change(m["scenes"][layout.local_index(index)]))


def _validate(root: Path, *args: str) -> tuple[int, list[str]]:
    proc = run_cli("validate", root, *args, check=False, timeout=TIMEOUT)
    return proc.returncode, proc.stdout.splitlines()


def _scene_of_split(root: Path, split: str) -> int:
    rows = manifest.read_manifest(root / "manifest.parquet").to_pylist()
    return next(r["scene"] for r in rows if r["split"] == split)


# ---------------------------------------------------------------- checksums in records


def test_records_hold_the_sha256_of_every_scene_file(default_dataset):
    """Each .records file and its metadata.json entry carry the SHA-256 of every scene file."""
    meta = json.loads((default_dataset / "0" / "metadata.json").read_text())
    for s in meta["scenes"]:
        record = json.loads(layout.record_path(default_dataset, s["index"]).read_text())
        assert record == s
        names = layout.scene_files(s)
        assert len(names) == 20 and sorted(s["sha256"]) == names
        for name in names:
            assert s["sha256"][name] == formats.file_sha256(default_dataset / "0" / name)
    rc, lines = _validate(default_dataset)
    assert rc == 0 and not [line for line in lines if line.startswith("note:")], lines


def _swap_pngs(root: Path) -> None:
    a, b = root / "0" / "RGB_0001_02.png", root / "0" / "RGB_0002_05.png"
    tmp = a.with_name("swap")
    a.rename(tmp), b.rename(a), tmp.rename(b)


def _double_depth(root: Path) -> None:
    path = root / "0" / "depth_0001_03.exr"
    formats.write_depth_exr(path, formats.read_depth_exr(path) * 2)


def _edit_seed(root: Path) -> None:
    _edit_json(root / "dataset.json", lambda d: d.update(seed=d["seed"] + 1))


def _edit_info(change: Callable[[dict], None]) -> Callable[[Path], None]:
    """Edit dataset.json, then recompute its fingerprint (a consistent-looking edit)."""
    from stillbox_gen import config

    def edit(d: dict) -> None:
        change(d)
        d["fingerprint"] = config.from_dict(d["config"]).fingerprint()

    return lambda root: _edit_json(root / "dataset.json", edit)


def _edit_args(change: Callable[[dict], None]) -> Callable[[Path], None]:
    return lambda root: _edit_json(root / "0" / "metadata.json", lambda m: change(m["args"]))


CORRUPTIONS = {
    "two_pngs_swapped": (
        _swap_pngs,
        [
            "0/RGB_0001_02.png: SHA-256 differs from the record of scene 1",
            "0/RGB_0002_05.png: SHA-256 differs from the record of scene 2",
        ],
    ),
    "depth_times_2": (
        _double_depth,
        ["0/depth_0001_03.exr: SHA-256 differs from the record of scene 1"],
    ),
    "deleted_record": (
        lambda root: layout.record_path(root, 2).unlink(),
        ["0/.records/0002.json: missing record of scene 2"],
    ),
    "stray_file_in_chunk": (
        lambda root: (root / "0" / "notes.txt").write_text("x"),
        ["0/notes.txt: stray file (no scene record names it)"],
    ),
    "stray_file_at_root": (
        lambda root: (root / "README.txt").write_text("x"),
        ["README.txt: stray file at the dataset root"],
    ),
    "extra_frame_no_record_names": (
        lambda root: shutil.copy(root / "0" / "RGB_0000_00.png", root / "0" / "RGB_0004_00.png"),
        ["0/RGB_0004_00.png: stray file (no scene record names it)"],
    ),
    "edited_dataset_seed": (
        _edit_seed,
        ["dataset.json: seed 4 differs from config.seed 3", "dataset.json: seed 4 does not give"],
    ),
    # dataset.json against each chunk's metadata.json and the records (issue 21)
    "fov_60_fingerprint_recomputed": (
        _edit_info(lambda d: d["config"]["camera"].update(fov_deg=60.0)),
        [
            "0/metadata.json: args.config.camera.fov_deg is 90.0, but dataset.json gives 60.0",
            "0/metadata.json: scene 0: K [[",
        ],
    ),
    "split_scenes": (
        _edit_info(lambda d: d["split_scenes"].update(train=d["split_scenes"]["train"] + 1)),
        ["dataset.json: split_scenes {'train': "],
    ),
    "frames": (
        _edit_info(lambda d: d.update(frames=50)),
        ["dataset.json: frames 50 is not scenes x config.camera.frames (4 x 10)"],
    ),
    "render_samples": (
        _edit_info(lambda d: d["render"].update(samples=64)),
        ["dataset.json: render.samples is 64, but its config gives 4"],
    ),
    "versions": (
        _edit_info(lambda d: d["versions"].update({"stillbox-gen": "9.9"})),
        ["0/metadata.json: args.generator is 'stillbox-gen "],
    ),
    "metadata_args": (
        _edit_args(lambda a: a.update(displacement=0.2)),
        ["0/metadata.json: args.displacement is 0.2, but dataset.json gives 0.1"],
    ),
    "metadata_args_config": (
        _edit_args(lambda a: a["config"]["render"].update(samples=16)),
        ["0/metadata.json: args.config.render.samples is 16, but dataset.json gives 4"],
    ),
    "record_time_step": (
        lambda root: _edit_record(root, 2, lambda s: s.update(time_step=0.1)),
        ["0/metadata.json: scene 2: time_step 0.1 differs from dataset.json's config"],
    ),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_validate_names_the_corrupted_file(ds, case):
    """Each corruption fails validate (exit 1) with a line naming the file."""
    corrupt, expected = CORRUPTIONS[case]
    assert _validate(ds)[0] == 0
    corrupt(ds)
    rc, lines = _validate(ds)
    assert rc == 1, lines
    for text in expected:
        assert any(line.startswith(text) for line in lines), (text, lines)


def test_edited_seed_with_matching_config_and_fingerprint_still_fails(ds):
    """Rewriting dataset.json consistently (seed, config.seed, fingerprint) is caught by the
    scene seeds, which derive from (seed, k)."""
    from stillbox_gen import config

    def change(d: dict) -> None:
        d["seed"] = d["config"]["seed"] = 4
        d["fingerprint"] = config.from_dict(d["config"]).fingerprint()

    _edit_json(ds / "dataset.json", change)
    rc, lines = _validate(ds)
    assert rc == 1 and any(line.startswith("dataset.json: seed 4 does not give") for line in lines)


def test_quick_skips_checksums_and_says_so(ds):
    _swap_pngs(ds)
    rc, lines = _validate(ds, "--quick")
    assert rc == 0 and "note: --quick: checksums and pixels not checked" in lines


def test_dataset_without_checksums_is_noted_not_failed(ds):
    """Datasets written before checksums existed validate, with a note that their files'
    contents cannot be checked."""
    for k in range(4):
        _edit_record(ds, k, lambda s: s.pop("sha256"))
    rc, lines = _validate(ds)
    assert rc == 0, lines
    notes = [line for line in lines if line.startswith("note:")]
    assert notes == [
        "note: 4 of 4 scenes (from 0) have no checksums in their records (written before "
        "stillbox-gen recorded them): their files' contents cannot be checked"
    ]


# ---------------------------------------------------------------- paths that leave the dataset


def _loader_attack(ds: Path, tmp_path: Path, how: str) -> tuple[int, Path]:
    """Point frame 0 of a training scene of ``ds`` at a real frame of another dataset."""
    ref = tmp_path / "ref"
    shutil.copytree(ds, ref)
    k = _scene_of_split(ds, "train")
    outside = ref / "0" / layout.rgb_name(k, 0)
    if how == "dotdot":
        name = f"../../../ref/0/{outside.name}"  # from ds/0: ds, a, tmp_path
        assert (ds / "0" / name).resolve() == outside.resolve()
    elif how == "absolute":
        name = str(outside)
    else:
        name = outside.name
        (ds / "0" / name).unlink()
        os.symlink(outside, ds / "0" / name)
    if how != "symlink":
        _edit_record(ds, k, lambda s: s["rgb"].__setitem__(0, name))
    return k, outside


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_benchmark_loader_refuses_frames_outside_the_dataset(ds, tmp_path, monkeypatch, how):
    """The training loader raises DataError naming the record before reading any frame; it used
    to train silently on the other dataset's file."""
    from benchmark.core import data

    k, outside = _loader_attack(ds, tmp_path, how)
    opened: list[str] = []
    real_imread, real_depth = cv2.imread, formats.read_depth_exr
    monkeypatch.setattr(cv2, "imread", lambda p, *a: opened.append(p) or real_imread(p, *a))
    monkeypatch.setattr(formats, "read_depth_exr", lambda p: opened.append(p) or real_depth(p))
    with pytest.raises(data.DataError) as e:
        data.FrameStore(data.load_scenes(ds, "train"), progress=False)
    assert f"0/metadata.json: scene {k}: " in str(e.value)
    assert "leaves the dataset folder" in str(e.value) or "outside the dataset" in str(e.value)
    assert opened == []


def test_dataset_reader_refuses_frames_outside_the_dataset(ds, tmp_path):
    """stillbox_gen.dataset.Dataset, the reader behind every command: DatasetError naming the
    record when any scene asked for has a name leading outside; the other scenes still load."""
    from stillbox_gen.dataset import Dataset
    from stillbox_gen.errors import DatasetError

    k, _ = _loader_attack(ds, tmp_path, "dotdot")
    reader = Dataset(ds)
    with pytest.raises(DatasetError, match=f"0/metadata.json: scene {k}: path '../"):
        reader.scenes()
    others = [i for i in reader.indices() if i != k]
    assert [reader.scene(i).index for i in others] == others


def test_bench_cli_refuses_a_symlink_leaving_the_dataset_in_one_line(ds, tmp_path):
    """stillbox-bench: exit 2, one line naming the scene, the outside FIFO never opened."""
    fifo = _outside_fifo(tmp_path)
    k = _scene_of_split(ds, "train")
    for name in (layout.depth_name(k, 0), layout.rgb_name(k, 0)):
        (ds / "0" / name).unlink()
        os.symlink(fifo, ds / "0" / name)
    cmd = [sys.executable, "-m", "benchmark.cli", "run", "constant", "--data", str(ds),
           "--out", str(tmp_path / "run"), "--quiet"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("stillbox-bench: error: ") and f"scene {k}: " in lines[0]
    assert f"symlink to '{fifo}'" in lines[0]
    assert not (tmp_path / "run").exists()


def test_validate_reports_names_leaving_the_dataset(ds, tmp_path):
    """A '..' name and a symlink to a FIFO outside: both named, exit 1, the FIFO never opened."""
    fifo = _outside_fifo(tmp_path)
    _edit_record(ds, 0, lambda s: s["rgb"].__setitem__(0, "../../../outside/secret.png"))
    (ds / "0" / "RGB_0001_00.png").unlink()
    os.symlink(fifo, ds / "0" / "RGB_0001_00.png")
    rc, lines = _validate(ds)
    assert rc == 1
    assert (
        "0/metadata.json: scene 0: path '../../../outside/secret.png' has '..' and leaves the "
        "dataset folder" in lines
    ), lines
    assert (
        f"0/metadata.json: scene 1: 'RGB_0001_00.png' leads through a symlink to '{fifo}', "
        "outside the dataset folder" in lines
    ), lines


@pytest.mark.parametrize("how", ["absolute", "symlink"])
def test_preview_refuses_paths_leaving_the_dataset(ds, tmp_path, how):
    fifo = _outside_fifo(tmp_path)
    if how == "absolute":
        _edit_record(ds, 0, lambda s: s["rgb"].__setitem__(0, str(fifo)))
        words = f"absolute path '{fifo}'"
    else:
        (ds / "0" / "depth_0000_09.exr").unlink()
        os.symlink(fifo, ds / "0" / "depth_0000_09.exr")
        words = f"leads through a symlink to '{fifo}'"
    out = tmp_path / "sheet.png"
    proc = run_cli("preview", ds, "--out", out, check=False, timeout=TIMEOUT)
    assert_user_error(proc, "DATASET: ", "0/metadata.json: scene 0: ", words)
    assert not out.exists()


def test_stats_refuses_a_symlink_leaving_the_dataset(ds, tmp_path):
    fifo = _outside_fifo(tmp_path)
    (ds / "0" / "depth_0000_00.exr").unlink()
    os.symlink(fifo, ds / "0" / "depth_0000_00.exr")
    proc = run_cli("stats", ds, "--scenes", 1, check=False, timeout=TIMEOUT)
    assert_user_error(proc, "0/metadata.json: scene 0: ", f"symlink to '{fifo}'")
    assert not (ds / "stats.json").exists()
    new = tmp_path / "new" / "report"  # --out is created only once the measurements are done
    proc = run_cli("stats", ds, "--scenes", 1, "--out", new, check=False, timeout=TIMEOUT)
    assert_user_error(proc, "0/metadata.json: scene 0: ", f"symlink to '{fifo}'")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("name", ["dataset.json", "manifest.parquet"])
def test_dataset_files_that_are_symlinks_outside_are_refused(ds, tmp_path, name):
    """dataset.json or manifest.parquet as a symlink to a FIFO outside: validate names it (exit
    1), preview, stats and the reader refuse it in one line; the FIFO is never opened."""
    from stillbox_gen.dataset import Dataset
    from stillbox_gen.errors import DatasetError

    fifo = _outside_fifo(tmp_path)
    (ds / name).unlink()
    os.symlink(fifo, ds / name)
    words = f"'{name}' leads through a symlink to '{fifo}', outside the dataset folder"
    rc, lines = _validate(ds)
    assert rc == 1 and f"{name}: {words}" in lines, lines
    for args in (["preview", ds, "--out", tmp_path / "p.png"], ["stats", ds]):
        proc = run_cli(*args, check=False, timeout=TIMEOUT)
        assert_user_error(proc, f"DATASET: '{ds}': {words}")
    with pytest.raises(DatasetError, match="leads through a symlink"):
        Dataset(ds)
    if name == "dataset.json":  # merge reads no manifest of its sources
        proc = run_cli("merge", tmp_path / "m", ds, check=False, timeout=TIMEOUT)
        assert_user_error(proc, f"SOURCES: '{ds}': {words}")
        assert not (tmp_path / "m").exists()
    assert not (tmp_path / "p.png").exists() and not (ds / "stats.json").exists()


@pytest.fixture
def photo_ds(custom_dataset: Path, tmp_path: Path) -> Path:
    """A private copy of the dataset rendered with --textures, two levels below ``tmp_path``."""
    out = tmp_path / "a" / "ds"
    shutil.copytree(custom_dataset, out)
    return out


def test_a_photo_name_leading_outside_is_reported_and_never_opened(photo_ds, tmp_path):
    """A record's material image '../..' (opened as textures_dir / name by stats --flicker):
    validate names the record, stats refuses before rendering; the FIFO is never opened."""
    fifo = _outside_fifo(tmp_path)
    name = os.path.relpath(fifo, json.loads((photo_ds / "dataset.json").read_text())["config"][
        "materials"]["textures_dir"])  # fmt: skip
    _edit_record(photo_ds, 0, lambda s: s["box"]["material"].update(kind="image", image=name))
    rc, lines = _validate(photo_ds)
    line = f"0/metadata.json: scene 0: photo '{name}' is not one of the dataset's photos"
    assert rc == 1 and any(x.startswith(line) for x in lines), lines
    out = tmp_path / "report"
    proc = run_cli("stats", photo_ds, "--flicker", 1, "--out", out, check=False, timeout=TIMEOUT)
    assert_user_error(proc, line)
    assert not out.exists()


def test_texture_files_leading_outside_in_dataset_json_are_reported(photo_ds, tmp_path):
    """config.materials.texture_files edited to a '..' name, fingerprint recomputed, and the
    records naming it: validate reports both; stats --flicker refuses the records."""
    bad = "../outside/secret.png"

    def change(d: dict) -> None:
        d["config"]["materials"]["texture_files"] = [bad]

    def rename_photos(s: dict) -> None:
        for material in [p["material"] for p in s["primitives"]] + [s["box"]["material"]]:
            if material["image"] is not None:
                material["image"] = bad
        s["box"]["material"].update(kind="image", image=bad)

    _edit_info(change)(photo_ds)
    for k in range(3):
        _edit_record(photo_ds, k, rename_photos)
    rc, lines = _validate(photo_ds)
    assert rc == 1
    assert any(x.startswith(f"dataset.json: config.materials.texture_files names '{bad}'")
               for x in lines), lines  # fmt: skip
    assert f"0/metadata.json: scene 0: photo '{bad}' is not one of the dataset's photos " \
        "(config.materials)" in lines, lines  # fmt: skip
    proc = run_cli("stats", photo_ds, "--flicker", 1, check=False, timeout=TIMEOUT)
    assert_user_error(proc, f"scene 0: photo '{bad}' is not one of the dataset's photos")


def test_merge_does_not_write_outside_out_for_a_dotdot_record(ds, tmp_path):
    """A record naming '../../payload.txt' used to make merge write beside OUT."""
    _edit_json(layout.record_path(ds, 1), lambda s: s["rgb"].__setitem__(0, "../../payload.txt"))
    (ds.parent / "payload.txt").write_text("payload")  # what ds/0/../../payload.txt names
    out = tmp_path / "o" / "out"
    out.parent.mkdir()
    proc = run_cli("merge", out, ds, check=False, timeout=TIMEOUT)
    record = layout.record_path(ds, 1)
    assert_user_error(
        proc, f"SOURCES: {record}: scene 1: path '../../payload.txt' has '..' and leaves"
    )
    assert list(out.parent.iterdir()) == []  # refused before OUT is created


def test_merge_refuses_missing_scenes_before_creating_out(ds, tmp_path):
    """merge used to create OUT, copy the scenes it had, and only then refuse."""
    layout.record_path(ds, 2).unlink()
    out = tmp_path / "out"
    proc = run_cli("merge", out, ds, check=False, timeout=TIMEOUT)
    assert_user_error(proc, "SOURCES: the merge lacks 1 of 4 scenes (2), which no folder holds")
    assert not out.exists()


def test_merge_does_not_copy_a_source_symlink_leaving_the_source(ds, tmp_path):
    """A source frame that is a symlink to a FIFO outside: refused, the FIFO never opened."""
    fifo = _outside_fifo(tmp_path)
    (ds / "0" / "RGB_0002_00.png").unlink()
    os.symlink(fifo, ds / "0" / "RGB_0002_00.png")
    out = tmp_path / "out"
    proc = run_cli("merge", out, ds, check=False, timeout=TIMEOUT)
    assert_user_error(proc, "scene 2: 'RGB_0002_00.png' leads through a symlink", str(fifo))
    assert not (out / "0" / "RGB_0002_00.png").exists()


def test_merge_does_not_write_through_a_symlink_in_out(ds, tmp_path):
    """OUT's chunk folder is a symlink to a folder outside OUT holding scenes 0, 1 and 3: merge
    refuses to add scene 2 there, and that folder is left as it was."""
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(ds / "0", elsewhere)
    (elsewhere / ".records" / "0002.json").unlink()
    before = {p: p.read_bytes() for p in sorted(elsewhere.rglob("*")) if p.is_file()}
    out = tmp_path / "out"
    out.mkdir()
    shutil.copyfile(ds / "dataset.json", out / "dataset.json")
    os.symlink(elsewhere, out / "0")
    proc = run_cli("merge", out, ds, check=False, timeout=TIMEOUT)
    assert_user_error(proc, f"scene 2 in '{ds}'", "leads through a symlink", str(elsewhere))
    after = {p: p.read_bytes() for p in sorted(elsewhere.rglob("*")) if p.is_file()}
    assert after == before


def test_a_config_written_before_render_light_tree_keeps_its_meaning_and_fingerprint():
    """dataset.json configs of datasets rendered before render.light_tree existed lack the key:
    they read back with the light tree on (as they were rendered) and hash as they did, while
    the current default (off) is written out and so changes the fingerprint."""
    from stillbox_gen import config

    new = config.load_preset("stillbox")
    assert new.render.light_tree is False and new.to_dict()["render"]["light_tree"] is False
    old = new.to_dict()
    del old["render"]["light_tree"]
    cfg = config.from_dict(old)
    assert cfg.render.light_tree is True
    assert cfg.to_dict() == old and cfg.fingerprint() != new.fingerprint()
    assert config.from_dict(new.to_dict()) == new


def test_validate_names_a_chunk_folder_that_is_a_symlink_and_reads_nothing_through_it(ds, tmp_path):
    """A chunk folder replaced by a link to a copy outside: the link itself is the first problem
    (found by lstat), and nothing of the outside folder is listed or read."""
    outside = tmp_path / "elsewhere"
    shutil.move(ds / "0", outside)
    os.symlink(outside, ds / "0")
    (outside / "extra.txt").write_text("outside")  # would be a stray file if it were listed
    rc, lines = _validate(ds)
    assert rc == 1
    assert lines[0] == f"0/: a symbolic link (to '{outside}'); a dataset holds no links", lines
    assert not any("extra.txt" in line for line in lines), lines

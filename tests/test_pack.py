"""``stillbox-gen pack --format webdataset`` and its streaming reader (stillbox_gen.packed): the
shards hold exactly the folder's scenes, bit for bit, pack reproducibly, score the same, stream
through DataLoader workers once each, and are refused when corrupted; bad arguments write
nothing."""

from __future__ import annotations

import math
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_user_error, file_tree, invoke_cli

from benchmark.core.metrics import aggregate, image_metrics
from stillbox_gen.dataset import Dataset, Scene
from stillbox_gen.errors import DatasetError
from stillbox_gen.packed import INDEX_JSON, PackedDataset
from stillbox_gen.torch_dataset import StillBoxPackedPairs, StillBoxPairs

SHARD_SCENES = 1  # 4 scenes -> 4 shards: two per DataLoader worker


def _pack(dataset: Path, out: Path, *extra: object) -> None:
    result = invoke_cli("pack", dataset, "--format", "webdataset", "--out", out, *extra)
    assert result.returncode == 0, result.stderr


@pytest.fixture(scope="module")
def packed(default_dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pack") / "P"
    _pack(default_dataset, out, "--scenes-per-shard", SHARD_SCENES)
    return out


def _tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (names relative to it) and its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))}


def test_every_scene_reads_back_bit_identical(default_dataset, packed):
    folder = Dataset(default_dataset)
    pack = PackedDataset(packed)
    assert pack.indices() == folder.indices() and pack.splits == folder.splits
    assert len(pack.shards) == len(folder.indices()) // SHARD_SCENES
    seen = []
    for s in pack.scenes():
        f = folder.scene(s.index)
        assert isinstance(s, Scene)
        assert (s.index, s.split, s.frames, s.time_step) == (
            f.index,
            f.split,
            f.frames,
            f.time_step,
        )
        assert s.record == f.record
        for name in ("K", "cam2world", "speed"):
            assert np.array_equal(getattr(s, name), getattr(f, name)), name
        assert np.array_equal(s.relative_pose(0, 3), f.relative_pose(0, 3))
        assert np.array_equal(s.translation(1, 4), f.translation(1, 4))
        for i in range(f.frames):
            rgb, want = s.load_rgb(i), f.load_rgb(i)
            assert rgb.dtype == want.dtype == np.uint8 and np.array_equal(rgb, want)
            depth, want = s.load_depth(i), f.load_depth(i)
            assert depth.dtype == want.dtype == np.float32
            assert depth.tobytes() == want.tobytes()  # bits, NaN and 1e10 included
        seen.append(s.index)
    assert seen == folder.indices()
    assert pack.info == folder.info  # dataset.json copied
    assert (packed / "manifest.parquet").read_bytes() == (
        default_dataset / "manifest.parquet"
    ).read_bytes()


def test_shards_follow_the_documented_layout(packed):
    pack = PackedDataset(packed)
    shard = pack.shards[0]
    with tarfile.open(shard.path) as tar:
        members = tar.getmembers()
    names = [m.name for m in members]
    assert names == sorted(names)
    k = shard.scenes[0]
    frames = shard.frames[0]
    assert set(names) == {
        f"{k:07d}.json",
        *(f"{k:07d}.rgb_{f:02d}.png" for f in range(frames)),
        *(f"{k:07d}.depth_{f:02d}.exr" for f in range(frames)),
    }
    assert {(m.mtime, m.uid, m.gid, m.mode, m.uname, m.type) for m in members} == {
        (0, 0, 0, 0o644, "", tarfile.REGTYPE)
    }


def test_packing_twice_gives_identical_bytes(default_dataset, packed, tmp_path):
    _pack(default_dataset, tmp_path / "again", "--scenes-per-shard", SHARD_SCENES)
    first, again = _tree(packed), _tree(tmp_path / "again")
    assert sorted(first) == sorted(again)
    assert first == again


def test_packed_and_folder_score_the_same(default_dataset, packed):
    """A fixed predictor (the train median plus a term of the pair's colours, so that every RGB
    and depth value matters) scored with the benchmark's metrics on both sets."""
    median = float(
        np.median(
            np.concatenate(
                [
                    s.load_depth(i).ravel()
                    for s in Dataset(default_dataset).scenes("train")
                    for i in range(s.frames)
                ]
            )
        )
    )

    def scores(pairs) -> dict[str, float]:
        per_image: dict[str, list] = {}
        keyed = []
        for item in pairs:
            pred = median + 10 * item["images"].mean(dim=0)
            m = image_metrics(pred[None], item["depth"][None])
            keyed.append((item["scene"], item["frame"], m))
        for _, _, m in sorted(keyed, key=lambda x: x[:2]):  # the same order for both
            for name, value in m.items():
                per_image.setdefault(name, []).append(value)
        return aggregate({n: torch.cat(v) for n, v in per_image.items()})

    folder = scores(StillBoxPairs(default_dataset, split=None))
    pack = scores(StillBoxPackedPairs(packed, split=None))
    assert folder["images"] == len(StillBoxPairs(default_dataset, split=None)) > 0
    assert folder.keys() == pack.keys()
    for name, value in folder.items():
        assert value == pack[name] or (math.isnan(value) and math.isnan(pack[name])), name


def test_dataloader_workers_yield_every_pair_once(default_dataset, packed):
    pairs = StillBoxPairs(default_dataset, split=None)
    stream = StillBoxPackedPairs(packed, split=None)
    assert len(stream) == len(pairs)
    loader = torch.utils.data.DataLoader(stream, batch_size=None, num_workers=2)
    items = list(loader)
    keys = [(int(x["scene"]), int(x["frame"])) for x in items]
    wanted = [(pairs.scenes[k].index, i) for k, i in pairs.items]
    assert sorted(keys) == sorted(wanted) and len(set(keys)) == len(keys)
    assert keys == [(int(x["scene"]), int(x["frame"])) for x in loader]  # deterministic order
    for x in items:
        want = pairs[wanted.index((int(x["scene"]), int(x["frame"])))]
        for name in ("images", "depth", "K", "pose"):
            assert torch.equal(x[name], want[name]), name
    # two processes of two workers each: disjoint halves that cover the split
    halves = [
        {
            (int(x["scene"]), int(x["frame"]))
            for x in StillBoxPackedPairs(packed, None, rank=r, world_size=2)
        }
        for r in (0, 1)
    ]
    assert halves[0] and halves[1] and not halves[0] & halves[1]
    assert halves[0] | halves[1] == set(wanted)


def test_a_corrupted_shard_is_refused(packed, tmp_path):
    copy = tmp_path / "P"
    shutil.copytree(packed, copy)
    shard = copy / PackedDataset(copy).shards[1].name
    data = bytearray(shard.read_bytes())
    data[len(data) // 3] ^= 0x01  # one bit in a frame's bytes: same size, other SHA-256
    shard.write_bytes(bytes(data))
    pack = PackedDataset(copy)
    first = next(pack.scenes())  # shard 0 is intact and still read
    assert first.index == pack.shards[0].scenes[0]
    with pytest.raises(DatasetError) as e:
        list(pack.scenes())
    message = str(e.value)
    assert "\n" not in message and shard.name in message and "SHA-256" in message
    with pytest.raises(DatasetError, match=shard.name):  # before any of its scenes is yielded
        next(pack.read_shard(pack.shards[1]))
    with pytest.raises(DatasetError, match=shard.name):
        list(StillBoxPackedPairs(copy, split=None))


def test_a_pack_without_index_is_refused(packed, tmp_path):
    """What an interrupted pack leaves (its shards, no index.json) is not read."""
    copy = tmp_path / "P"
    shutil.copytree(packed, copy)
    (copy / INDEX_JSON).unlink()
    with pytest.raises(DatasetError, match="no index.json"):
        PackedDataset(copy)


def test_an_interrupted_pack_leaves_nothing(default_dataset, tmp_path, monkeypatch):
    from stillbox_gen import pack

    real, calls = pack._write_shard, []

    def interrupted(f, scenes):
        calls.append(1)
        if len(calls) == 3:  # in the middle of the third shard
            f.write(b"half a shard")
            raise KeyboardInterrupt
        return real(f, scenes)

    monkeypatch.setattr(pack, "_write_shard", interrupted)
    out = tmp_path / "P"
    with pytest.raises(KeyboardInterrupt):
        pack.pack_webdataset(default_dataset, out, scenes_per_shard=1)
    assert len(calls) == 3 and not out.exists()


@pytest.mark.parametrize("case", ["not empty", "a file", "inside the dataset", "zero per shard"])
def test_bad_out_is_refused_and_nothing_written(default_dataset, tmp_path, case):
    source, out = default_dataset, tmp_path / "P"
    words = ["--out"]
    extra: list[object] = []
    if case == "not empty":
        out.mkdir()
        (out / "notes.txt").write_text("mine")
        words.append("not empty")
    elif case == "a file":
        out.write_text("mine")
        words.append("is a file")
    elif case == "inside the dataset":  # in a copy: a bug must not write into the shared one
        source = tmp_path / "D"
        shutil.copytree(default_dataset, source)
        out = source / "packed"
        words.append("inside the dataset")
    else:
        extra, words = ["--scenes-per-shard", 0], ["--scenes-per-shard"]
    before = file_tree(source)
    existed = _tree(out) if out.is_dir() else out.read_bytes() if out.exists() else None
    result = invoke_cli("pack", source, "--out", out, *extra)
    assert_user_error(result, *words)
    after = _tree(out) if out.is_dir() else out.read_bytes() if out.exists() else None
    assert after == existed
    assert file_tree(source) == before


def test_a_folder_that_is_no_valid_dataset_is_refused(default_dataset, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    result = invoke_cli("pack", empty, "--out", tmp_path / "P1")
    assert_user_error(result, "DATASET", "dataset.json", "stillbox-gen validate")
    result = invoke_cli("pack", tmp_path / "nothing", "--out", tmp_path / "P1")
    assert_user_error(result, "DATASET", "is not a folder")
    # a frame changed after it was written: found while packing, in validate's words, and the
    # shards already written are deleted
    changed = tmp_path / "D"
    shutil.copytree(default_dataset, changed)
    last = Dataset(changed).scenes()[-1]
    data = bytearray(last.rgb[0].read_bytes())
    data[-20] ^= 0x01
    last.rgb[0].write_bytes(bytes(data))
    result = invoke_cli("pack", changed, "--out", tmp_path / "P2", "--scenes-per-shard", 1)
    assert_user_error(result, "DATASET", last.rgb[0].name, "SHA-256 differs from the record")
    assert not (tmp_path / "P1").exists() and not (tmp_path / "P2").exists()


def test_the_benchmarks_evaluation_pairs_are_the_same(default_dataset, packed):
    """The benchmark's own loader (FrameStore, PairDataset in eval mode) over the packed scenes
    gives the folder's batches, and so the same scores for any network."""
    from benchmark.core.data import FrameStore, PairDataset

    folder = PairDataset(FrameStore(Dataset(default_dataset).scenes(), progress=False), "eval")
    pack = PairDataset(FrameStore(list(PackedDataset(packed).scenes()), progress=False), "eval")
    assert len(folder) == len(pack) > 0
    a, b = folder.batch(list(range(len(folder)))), pack.batch(list(range(len(pack))))
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name
    pred = a["input"].mean(dim=1).exp()  # any deterministic function of the frames
    assert aggregate(image_metrics(pred, a["target"])) == aggregate(
        image_metrics(pred, b["target"])
    )


def test_pack_versions_one_and_two_are_read_and_others_refused(packed, tmp_path):
    """pack_version 1 (before the --flow files were packed) is read as 2 is; an unknown version
    is refused in one line naming index.json."""
    import json

    assert PackedDataset(packed).index["pack_version"] == 2
    copy = tmp_path / "P"
    shutil.copytree(packed, copy)
    index = json.loads((copy / INDEX_JSON).read_text())
    for version in (1, 3):
        (copy / INDEX_JSON).write_text(json.dumps({**index, "pack_version": version}))
        if version == 1:
            scenes = list(PackedDataset(copy).scenes())
            assert [s.index for s in scenes] == PackedDataset(packed).indices()
            assert all(s.flow_files == {} for s in scenes)
        else:
            with pytest.raises(DatasetError, match="index.json: pack_version 3") as e:
                PackedDataset(copy)
            assert "\n" not in str(e.value)

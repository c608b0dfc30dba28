"""Supervised pairs from a rotating dataset (the thesis' "D + O" DepthNet): each pair's reference
is stabilised to its target's orientation by the known rotation (core.data.PairDataset). Checked
on a real render: the same input as eval-sequences' stabilisation (the unsupervised code's
inverse warp), a translation-only flow from the target's depth and the pair's translation then
carries the stabilised reference onto the target, a flip commutes with the stabilisation, the
batched path equals the per-item one, and `run depthnet-tiny` trains and scores on such data."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_bench import bench
from torch.utils.data import default_collate

from benchmark.core.data import FrameStore, PairDataset, load_scenes, normalise
from benchmark.core.flow import flow_from_depth, warp
from benchmark.unsupervised.reprojection import rotate_frame


@pytest.fixture(scope="module")
def rotating_pairs(rotating_dataset) -> PairDataset:
    """Every 2-frame forward pair of the rotating dataset's training scene (5° a frame)."""
    scenes = load_scenes(rotating_dataset, "train", rotations=True)
    return PairDataset(FrameStore(scenes, progress=False), "eval", shift=2)


def test_the_reference_is_stabilised_as_eval_sequences_stabilises_it(rotating_pairs):
    """Each pair's input: the target frame as it is, the reference turned to the target's axes
    by the unsupervised code's rotate_frame (mid-grey, 0, where the reference does not see),
    and the translation the camera centre's move in the target's axes."""
    store = rotating_pairs.store
    for i in range(len(rotating_pairs)):
        item = rotating_pairs[i]
        k, scene = 0, store.scenes[0]  # the training split's one scene
        i1, i2 = item["frames"].tolist()
        turn = torch.from_numpy(scene.relative_pose(i2, i1)[:3, :3]).float()[None]
        raw = torch.from_numpy(normalise(store.rgb(k, i1)))[None]
        expected, seen = rotate_frame(raw, turn, torch.from_numpy(scene.K).float()[None])
        expected = torch.where(seen, expected, 0.0)[0]
        # away from the frame's edge, where one path's border pixel is the other's outside
        inner = torch.zeros_like(seen[0, 0])
        inner[1:-1, 1:-1] = True
        inside = seen[0, 0] & inner
        torch.testing.assert_close(item["input"][:3][:, inside], expected[:, inside], atol=2e-4,
                                   rtol=0)  # fmt: skip
        assert seen.float().mean() < 0.995  # a 10° turn leaves part of the frame unseen
        assert torch.equal(item["input"][3:], torch.from_numpy(normalise(store.rgb(k, i2))))
        centres = scene.cam2world[[i1, i2], :3, 3]
        move = scene.cam2world[i2, :3, :3].T @ (centres[1] - centres[0])
        np.testing.assert_allclose(item["translation"].numpy(), move, atol=1e-5)


def test_a_translation_flow_carries_the_stabilised_reference_onto_the_target(rotating_pairs):
    """With the rotation removed, the pair is a pure translation: the flow of the target's depth
    and the pair's translation (core.flow) warps the stabilised reference onto the target; the
    same flow on the reference as rendered (not stabilised) does not."""
    store = rotating_pairs.store
    for i in range(len(rotating_pairs)):
        item = rotating_pairs[i]
        i1, i2 = item["frames"].tolist()
        depth = torch.from_numpy(store.depth(0, i2)).double()
        flow = flow_from_depth(depth, item["K"].double(), -item["translation"].double())
        flow = flow.float()[None]
        target = item["input"][None, 3:]
        errors = []
        for reference in (
            item["input"][None, :3],
            torch.from_numpy(normalise(store.rgb(0, i1)))[None],
        ):
            moved, inside = warp(reference, flow)
            seen = inside & (moved.abs().sum(1) > 0)  # and inside the stabilised reference
            errors.append(float((moved - target).abs().sum(1)[seen].mean()))
        assert errors[0] < 0.4 * errors[1], errors


@pytest.mark.parametrize("flip_h, flip_v", [(True, False), (False, True), (True, True)])
def test_a_flip_commutes_with_the_stabilisation(rotating_pairs, flip_h, flip_v):
    """The stabilised input of a flipped pair (its homography mirrored) is the flipped
    stabilised input of the pair, to interpolation precision."""
    store, (i1, i2) = rotating_pairs.store, (0, 3)
    pairs = []
    for flips in ((False, False), (flip_h, flip_v)):
        view = (slice(None, None, -1 if flips[1] else 1), slice(None, None, -1 if flips[0] else 1))
        x = np.concatenate([normalise(store.rgb(0, f)[view]) for f in (i1, i2)])[None]
        _, _, homography = rotating_pairs._camera(0, i1, i2, *flips)
        rotating_pairs._stabilise(x, [homography])
        pairs.append(torch.from_numpy(x[0]))
    dims = [d for d, flip in ((2, flip_h), (1, flip_v)) if flip]
    torch.testing.assert_close(pairs[1], pairs[0].flip(dims), atol=1e-4, rtol=0)


def test_batches_equal_items_on_rotating_pairs(rotating_dataset):
    """The training path: a batch is the collated items bit for bit, stabilised references and
    flips included."""
    scenes = load_scenes(rotating_dataset, "train", rotations=True)
    pairs = PairDataset(FrameStore(scenes, progress=False), "train", seed=3)
    indices = list(range(len(pairs)))
    batch = pairs.batch(indices, epoch=1)
    pairs.set_epoch(1)
    items = default_collate([pairs[i] for i in indices])
    for key in ("input", "target", "translation", "K", "frames", "flips"):
        assert torch.equal(batch[key], items[key]), key
    turned = [j for j in indices if len(set(batch["frames"][j].tolist())) == 2]
    assert turned and batch["flips"].any()


def test_run_depthnet_trains_and_scores_on_rotating_data(rotating_dataset, tmp_path):
    """`run depthnet-tiny` on a rotating dataset (refused before pairs were stabilised): two
    steps, then its test score."""
    bench("run", "depthnet-tiny", "--data", rotating_dataset, "--batch-size", 2, "--max-steps", 2,
          "--quiet", "--out", tmp_path / "d")  # fmt: skip
    summary = json.loads((tmp_path / "d" / "summary.json").read_text())
    assert np.isfinite(summary["metrics"]["mae"]) and summary["metrics"]["images"] > 0

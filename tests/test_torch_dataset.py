"""stillbox_gen.torch_dataset: the pair and sequence datasets read what the files hold, through a
DataLoader with worker processes, in the conventions they state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT
from stillbox_gen.dataset import Dataset
from stillbox_gen.torch_dataset import StillBoxPairs, StillBoxSequences


def test_pairs_through_workers_match_the_files(default_dataset):
    pairs = StillBoxPairs(default_dataset, split=None)
    scenes = Dataset(default_dataset).scenes()
    assert len(pairs) == sum(s.frames - NOMINAL_SHIFT for s in scenes)
    loader = torch.utils.data.DataLoader(pairs, batch_size=5, num_workers=2)
    batch = next(iter(loader))
    assert batch["images"].shape[:2] == (5, 6) and batch["images"].dtype == torch.float32
    for b in range(5):
        scene = scenes[[s.index for s in scenes].index(int(batch["scene"][b]))]
        i = int(batch["frame"][b])
        j = i + NOMINAL_SHIFT
        first = torch.from_numpy(scene.load_rgb(i)).permute(2, 0, 1).float() / 255
        assert torch.equal(batch["images"][b, :3], first)
        depth = scene.load_depth(j)
        assert np.array_equal(batch["depth"][b].numpy(), np.minimum(depth, MAX_DEPTH))
        # the pose carries a point seen in frame i into frame j's camera: the known motion
        moved = batch["pose"][b].double().numpy() @ np.array([0.0, 0.0, 10.0, 1.0])
        expected = np.array([0.0, 0.0, 10.0]) - scene.translation(i, j)
        assert np.allclose(moved[:3], expected, atol=1e-4)
    assert float(batch["depth"].max()) <= MAX_DEPTH


def test_sequences_are_windows_with_poses_from_their_first_frame(default_dataset):
    scenes = Dataset(default_dataset).scenes()
    seqs = StillBoxSequences(default_dataset, split=None, length=4, stride=3)
    assert len(seqs) == sum(len(range(0, s.frames - 3, 3)) for s in scenes)
    item = seqs[1]
    scene = scenes[0]
    assert (item["scene"], item["frame"]) == (scene.index, 3)
    assert item["images"].shape[:2] == (4, 3) and item["depth"].shape[0] == 4
    assert torch.allclose(item["poses"][0], torch.eye(4), atol=1e-6)
    for f in range(4):
        expected = torch.from_numpy(scene.relative_pose(3, 3 + f)).float()
        assert torch.equal(item["poses"][f], expected)
        assert np.array_equal(item["depth"][f].numpy(), np.minimum(scene.load_depth(3 + f), 100))


def test_bad_arguments_are_refused(default_dataset):
    with pytest.raises(ValueError, match="shift"):
        StillBoxPairs(default_dataset, shift=0)
    with pytest.raises(ValueError, match="length"):
        StillBoxSequences(default_dataset, length=1)

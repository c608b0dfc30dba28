"""The toy-problem study (benchmark.unsupervised.toy and its command; thesis §4.6, Table 4.1).

Fast tests check the metrics, ΔM and the table on hand-made numbers, the command's one-line
errors and the saved runs of --resume (read back exactly; a study resumed after an interruption
gives the uninterrupted one's results); the render tests render both toy presets at 64 px (about
3 s each) and run the study on them: `--quick` end to end (and interrupted, then resumed), the
photometric loss at the true depth, and that a grid point optimised in the batch follows the
trajectory it follows alone."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import click
import numpy as np
import pytest
import torch
from conftest import TOY_RES as RES

from benchmark.cli.options import UserError
from benchmark.cli.unsupervised import DEPTHS_NPZ, RESULTS_JSON, TABLE_MD, toy_cmd
from benchmark.unsupervised import toy, toy_runs
from benchmark.unsupervised.reprojection import SMOOTH_LOSSES, inverse_warp, photometric_loss

# ---------------------------------------------------------------- metrics (fast)


def test_log_error_is_the_mean_absolute_log_ratio_over_valid_pixels():
    truth = torch.tensor([[[[1.0, 2.0], [4.0, 1e10]]]])
    valid = truth <= 100
    est = torch.tensor([[[[1.0, 2.0], [4.0, 7.0]]], [[[np.e, 2.0], [4.0, 1.0]]]])
    le = toy.log_error(est, truth, valid)
    np.testing.assert_allclose(le.numpy(), [0.0, 1 / 3], rtol=1e-6)  # the sky pixel is left out


def test_quality_is_normalised_and_a_geometric_mean():
    assert toy.scene_quality(0.0, 0.5) == 1.0
    assert toy.scene_quality(0.25, 0.5) == 0.5
    assert toy.scene_quality(0.7, 0.5) == 0.0  # worse than the start: 0, not negative
    assert toy.quality([0.25, 1.0]) == pytest.approx(0.5)
    assert toy.quality([0.0, 1.0]) == 0.0  # one failed scene fails the pair
    np.testing.assert_allclose(toy.quality([np.array([0.64, 1.0]), np.array([1.0, 0.25])]),
                               [0.8, 0.5])  # fmt: skip


def test_robustness_is_the_mean_slope_per_decade_around_the_optimum():
    lambdas, kappas = (0.1, 1.0, 10.0), (0.1, 0.3, 1.0)
    flat = np.full((3, 3), 0.5)
    assert toy.robustness(flat, (1, 1), lambdas, kappas) == 0.0
    m = np.array([[0.0, 0.4, 0.0], [0.2, 0.8, 0.5], [0.0, 0.6, 0.0]])
    k = np.log10(3)  # decades between κ = 0.1 and 0.3 (0.3 and 1: log10(10/3))
    expected = np.mean([0.4 / 1, 0.2 / 1, 0.6 / k, 0.3 / (1 - k)])
    assert toy.robustness(m, (1, 1), lambdas, kappas) == pytest.approx(expected)
    corner = np.array([[0.9, 0.5], [0.3, 0.1]])  # two neighbours only
    assert toy.robustness(corner, (0, 0), (1.0, 10.0), (0.1, 1.0)) == pytest.approx(0.5)


def test_grid_is_lambda_major_and_thesis_table_covers_every_loss():
    cfg = toy.StudyConfig(lambdas=(1.0, 2.0), kappas=(0.1, 0.2, 0.3))
    lam, kap = toy.grid(cfg)
    assert lam.tolist() == [1, 1, 1, 2, 2, 2]
    assert kap.tolist() == pytest.approx([0.1, 0.2, 0.3] * 2)
    assert set(toy.THESIS_TABLE_4_1) == set(SMOOTH_LOSSES)
    assert toy.thesis_value("diffusion", True, "delta_m") == 1.05
    assert toy.thesis_value("robust_diffusion", False, "lambda") == 100


# ---------------------------------------------------------------- command errors (fast)


def _invoke(*args: object) -> None:
    toy_cmd.main([str(a) for a in args], standalone_mode=False)


def _random_scene(name: str, seed: int, size: int = 24) -> toy.ToyScene:
    """A toy scene of noise frames, a random depth and two lateral-and-forward poses."""
    gen = torch.Generator().manual_seed(seed)
    f, c = size / 2, (size - 1) / 2
    depth = 2 + 8 * torch.rand(1, 1, size, size, generator=gen)
    poses = [
        (torch.eye(3), torch.tensor([0.1, -0.1, 0.2])),
        (torch.eye(3), torch.tensor([-0.1, 0.1, -0.2])),
    ]
    return toy.ToyScene(
        name=name,
        frames=torch.rand(3, 3, size, size, generator=gen),
        depth=depth,
        valid=depth > 0,
        K=torch.tensor([[f, 0, c], [0, f, c], [0, 0, 1.0]]),
        poses=poses,
    )


def test_batched_photometric_loss_is_the_per_reference_one():
    """Problem.photometric (precomputed rays, both references in one batch) equals
    photometric_loss over each reference's inverse_warp, with and without occlusion masks."""
    scenes = [_random_scene("horizon", 0), _random_scene("flower", 1)]
    problem = toy.Problem(scenes, torch.tensor([1.0, 3.0]), torch.tensor([0.3, 1.0]))
    gen = torch.Generator().manual_seed(2)
    depth = 2 + 8 * torch.rand(problem.truth.shape, generator=gen)
    occluded = [torch.rand(problem.truth.shape, generator=gen) < 0.2 for _ in toy.REFERENCES]
    for occ in (None, occluded):
        d = depth.clone().requires_grad_(True)
        got = problem.photometric(d, occ)
        got.sum().backward()
        d2 = depth.clone().requires_grad_(True)
        warps = [
            inverse_warp(ref, d2, r, t, problem.K)
            for ref, (r, t) in zip(problem.references, problem.poses, strict=True)
        ]
        masks = (
            [v for _, v in warps]
            if occ is None
            else [v & ~o for (_, v), o in zip(warps, occ, strict=True)]
        )
        expected = photometric_loss(problem.target, [w for w, _ in warps], masks, alpha=0.0)
        expected.sum().backward()
        assert masks[0].float().mean() > 0.5
        torch.testing.assert_close(got, expected, rtol=1e-6, atol=0)
        scale = d2.grad.abs().max()
        torch.testing.assert_close(d.grad / scale, d2.grad / scale, rtol=0, atol=1e-5)


# ---------------------------------------------------------------- --resume (fast)

#: results.json entries that are times (they differ between any two studies)
TIMINGS = ("seconds", "cpu_seconds", "seconds_per_iteration")


def _untimed(results: dict) -> dict:
    """results.json without its timings."""
    if isinstance(results, dict):
        return {k: _untimed(v) for k, v in results.items() if k not in TIMINGS}
    return results


def _tiny_study() -> tuple[list[toy.ToyScene], toy.StudyConfig]:
    scenes = [_random_scene("horizon", 0, 16), _random_scene("flower", 1, 16)]
    cfg = toy.StudyConfig(iterations=4, lambdas=(1.0, 30.0), kappas=(0.3,), odm_every=2,
                          losses=("tv", "diffusion"))  # fmt: skip
    return scenes, cfg


class Interrupt(Exception):
    pass


def test_saved_runs_read_back_exactly_and_a_resumed_study_is_the_uninterrupted_one(tmp_path):
    """run_study interrupted at the start of its 4th run (of 5), its 3 finished runs saved by
    toy_runs and read back, then resumed: the same results (timings apart) and BestRuns, bit
    for bit, and only the missing runs computed."""
    scenes, cfg = _tiny_study()
    whole, whole_best = toy.run_study(scenes, cfg)
    settings = toy_runs.settings(cfg, scenes)
    toy_runs.start(tmp_path, settings)
    started = []

    def on_run(key: str) -> None:
        if len(started) == 3:
            raise Interrupt
        started.append(key)

    def save(key, block, best):
        toy_runs.save(tmp_path, key, block, best, settings)

    with pytest.raises(Interrupt):
        toy.run_study(scenes, cfg, on_run=on_run, on_done=save)
    keys = toy_runs.finished(tmp_path)
    assert started == ["photometric", "tv/odm-off", "tv/odm-on"] and keys == sorted(started)
    assert toy_runs.read_settings(tmp_path) == settings
    done = {k: toy_runs.load(tmp_path, k, settings) for k in keys}
    for key, (block, best) in done.items():
        expected = whole["photometric"] if key == "photometric" else whole["runs"][key]
        assert _untimed(block) == _untimed(expected) and block["seconds"] >= 0
        assert best.label == key and best.history_iterations == [0, 1, 2, 3, 4]
        for n in toy.SCENES:
            assert best.depth[n].dtype == torch.float32 and best.depth[n].shape == (1, 1, 16, 16)
    assert done["tv/odm-off"][1].occluded["flower"] is None
    masks = done["tv/odm-on"][1].occluded["flower"]
    assert len(masks) == 2 and masks[0].dtype == torch.bool and masks[0].shape == (1, 1, 16, 16)
    rest = []
    resumed, resumed_best = toy.run_study(scenes, cfg, on_run=rest.append, done=done)
    assert rest == ["diffusion/odm-off", "diffusion/odm-on"]
    assert json.dumps(_untimed(resumed)) == json.dumps(_untimed(whole))
    for key, b in whole_best.items():
        r = resumed_best[key]
        for n in toy.SCENES:
            assert torch.equal(r.depth[n], b.depth[n]) and np.array_equal(
                r.history[n], b.history[n]
            )
            assert r.history[n].dtype == b.history[n].dtype
            if b.occluded[n] is None:
                assert r.occluded[n] is None
            else:
                assert all(
                    torch.equal(x, y) for x, y in zip(r.occluded[n], b.occluded[n], strict=True)
                )
    toy_runs.remove(tmp_path)
    assert not toy_runs.folder(tmp_path).exists() and toy_runs.finished(tmp_path) == []


def test_halves_run_apart_combine_into_the_whole_study(tmp_path):
    """Two studies of half the losses each, in two folders (two processes, one per core): their
    run files copied into one folder and resumed with every loss give the whole study's
    results, computing nothing; the CLI takes only the runs the resumed study asks for."""
    from benchmark.cli.unsupervised import _check_resume

    scenes, cfg = _tiny_study()
    whole, _ = toy.run_study(scenes, cfg)
    for loss in cfg.losses:
        half = dataclasses.replace(cfg, losses=(loss,))
        settings = toy_runs.settings(half, scenes)
        toy_runs.start(tmp_path / loss, settings)
        toy.run_study(scenes, half, on_done=lambda k, blk, b, o=tmp_path / loss, st=settings:
                      toy_runs.save(o, k, blk, b, st))  # fmt: skip
    combined = tmp_path / "whole"
    shutil.copytree(toy_runs.folder(tmp_path / "tv"), toy_runs.folder(combined))
    for f in toy_runs.folder(tmp_path / "diffusion").glob("diffusion.*.npz"):
        shutil.copy(f, toy_runs.folder(combined))
    settings = toy_runs.settings(cfg, scenes)
    assert toy_runs.difference(toy_runs.read_settings(combined), settings) is None
    keys = _check_resume(combined, settings, resume=True)
    assert len(keys) == 5
    done = {k: toy_runs.load(combined, k, settings) for k in keys}
    computed = []
    resumed, _ = toy.run_study(scenes, cfg, on_run=computed.append, done=done)
    assert computed == [] and json.dumps(_untimed(resumed)) == json.dumps(_untimed(whole))
    tv_only = toy_runs.settings(dataclasses.replace(cfg, losses=("tv",)), scenes)
    assert sorted(_check_resume(combined, tv_only, resume=True)) == [
        "photometric", "tv/odm-off", "tv/odm-on"]  # fmt: skip


def test_runs_computed_alone_or_by_worker_processes_are_the_study_s(tmp_path):
    """compute_run gives each run of run_study bit for bit; toy_jobs.run_parallel (2 spawned
    workers) hands every run to on_done, costliest first, and run_study assembles the same
    study from them, computing nothing."""
    from benchmark.unsupervised import toy_jobs

    scenes, cfg = _tiny_study()
    whole, whole_best = toy.run_study(scenes, cfg)
    assert toy.run_keys(cfg) == ["photometric", "tv/odm-off", "tv/odm-on", "diffusion/odm-off",
                                 "diffusion/odm-on"]  # fmt: skip
    block, best = toy.compute_run(scenes, cfg, "diffusion/odm-on")
    assert _untimed(block) == _untimed(whole["runs"]["diffusion/odm-on"])
    assert torch.equal(best.depth["flower"], whole_best["diffusion/odm-on"].depth["flower"])
    keys = ["photometric", "tv/odm-off", "robust_diffusion/odm-on", "diffusion/odm-off"]
    assert toy_jobs.schedule(keys) == ["robust_diffusion/odm-on", "tv/odm-off",
                                       "diffusion/odm-off", "photometric"]  # fmt: skip
    seen, reported = [], []
    done = {"photometric": (whole["photometric"], whole_best["photometric"])}
    computed = toy_jobs.run_parallel(
        scenes, cfg, 2, done, lambda k, b, r: seen.append(k), reported.append
    )
    assert sorted(seen) == sorted(computed) == sorted(toy.run_keys(cfg)[1:])
    assert sum(reported) == len(computed) * cfg.iterations  # the workers' progress, all of it
    rest = []
    assembled, _ = toy.run_study(scenes, cfg, on_run=rest.append, done={**done, **computed})
    assert rest == [] and json.dumps(_untimed(assembled)) == json.dumps(_untimed(whole))


def test_a_worker_reports_its_iterations_as_it_goes(monkeypatch):
    """A worker's run puts its iterations on the progress queue every PROGRESS_EVERY and the
    remainder at its end (here 4 iterations, reports of 3: then 3 and 1)."""
    import queue

    from benchmark.unsupervised import toy_jobs

    scenes, cfg = _tiny_study()
    monkeypatch.setattr(toy_jobs, "PROGRESS_EVERY", 3)
    monkeypatch.setattr(toy_jobs, "_progress", queue.Queue())
    key, _, _ = toy_jobs._run(scenes, cfg, "tv/odm-on")
    assert key == "tv/odm-on"
    reports = []
    toy_jobs._drain(toy_jobs._progress, reports.append)
    assert reports == [3, 1]


def test_resume_settings_name_what_changed_and_bad_run_files_are_one_line_errors(tmp_path):
    scenes, cfg = _tiny_study()
    settings = toy_runs.settings(cfg, scenes)
    assert toy_runs.difference(settings, json.loads(json.dumps(settings))) is None
    other = toy_runs.settings(dataclasses.replace(cfg, iterations=5), scenes)
    assert toy_runs.difference(settings, other) == "--iterations 4, now 5"
    changed = [scenes[0], _random_scene("flower", 2, 16)]
    assert toy_runs.difference(settings, toy_runs.settings(cfg, changed)) == "other --flower data"
    toy_runs.start(tmp_path, settings)
    best = toy.BestRun("photometric", {"flower": torch.ones(1, 1, 2, 2)}, {"flower": None},
                       {"flower": np.zeros(3, np.float32)}, [0, 1, 2])  # fmt: skip
    toy_runs.save(tmp_path, "photometric", {"m": 0.5}, best, settings)
    with pytest.raises(ValueError, match=r"photometric\.npz' is not a readable toy run \(run "
                       "with other settings"):  # fmt: skip
        toy_runs.load(tmp_path, "photometric", other)
    path = toy_runs.run_path(tmp_path, "photometric")
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(
        ValueError, match=r"^'.*photometric\.npz' is not a readable toy run \(.*\); remove it$"
    ):
        toy_runs.load(tmp_path, "photometric", settings)
    (toy_runs.folder(tmp_path) / toy_runs.STUDY_JSON).write_text("{")
    with pytest.raises(ValueError, match="study.json' is not a readable toy study"):
        toy_runs.read_settings(tmp_path)


def test_missing_dataset_names_the_option_and_the_command_that_renders_it(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(UserError) as e:
        _invoke("--flower", tmp_path / "nope", "--horizon", tmp_path / "nope2", "--out", out)
    assert e.value.exit_code == 2
    msg = e.value.format_message()
    assert "--horizon" in msg and "stillbox-gen --preset toy-horizon --out" in msg
    assert "\n" not in msg and not out.exists()


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (("--lambdas", "1,x"), "--lambdas"),
        (("--kappas", "0.3,-1"), "--kappas"),
        (("--losses", "diffusion,blur"), "--losses"),
        (("--iterations", "0"), "--iterations"),
        (("--odm-every", "0"), "--odm-every"),
        (("--device", "tpu"), "--device"),
    ],
)
def test_bad_options_are_one_line_errors(tmp_path, args, flag):
    # a UserError, or click's own for a number beyond benchmark/cli/limits.py's bounds (whose
    # message names the flag when formatted: "Invalid value for '--iterations': ...")
    with pytest.raises(click.ClickException) as e:
        _invoke("--out", tmp_path / "out", *args)
    assert e.value.exit_code == 2 and flag in e.value.format_message()
    assert not (tmp_path / "out").exists()


def test_out_that_is_a_file_is_refused_and_kept(tmp_path):
    out = tmp_path / "out"
    out.write_text("keep")
    with pytest.raises(UserError, match=f"^--out: '{out}' is a file, not a folder$"):
        _invoke("--out", out)
    assert out.read_text() == "keep"


def test_without_numba_the_toy_command_names_the_extra_to_install(tmp_path, monkeypatch):
    import sys

    import benchmark.unsupervised as package

    # numba as if not installed: the kernels module is imported afresh and fails on it
    monkeypatch.setitem(sys.modules, "numba", None)
    monkeypatch.delitem(sys.modules, "benchmark.unsupervised.toy_kernels", raising=False)
    monkeypatch.delattr(package, "toy_kernels", raising=False)
    with pytest.raises(UserError) as e:
        _invoke("--out", tmp_path / "out")
    assert str(e.value) == toy.NUMBA_MISSING and "stillbox-gen[toy]" in str(e.value)
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- on rendered toy scenes


@pytest.fixture(scope="module")
def scenes(toy_data) -> list[toy.ToyScene]:
    return [toy.load_scene(toy_data[n], n) for n in toy.SCENES]


@pytest.fixture(scope="module")
def quick_study(toy_data, tmp_path_factory) -> Path:
    """The output folder of an uninterrupted `--quick` study."""
    out = tmp_path_factory.mktemp("quick") / "study"
    _invoke("--flower", toy_data["flower"], "--horizon", toy_data["horizon"], "--out", out,
            "--quick", "--quiet")  # fmt: skip
    return out


@pytest.mark.render
def test_quick_study_end_to_end(quick_study):
    out = quick_study
    assert not toy_runs.folder(out).exists()  # the saved runs are gone once the study ends
    results = json.loads((out / RESULTS_JSON).read_text())
    assert results["iterations"] == toy.QUICK_ITERATIONS
    assert results["learning_rate"] == 0.15 and results["start_depth_m"] == 10.0
    assert set(results["runs"]) == {toy.run_key(n, o) for n in SMOOTH_LOSSES for o in (0, 1)}
    le0 = results["le0"]
    assert set(le0) == {"horizon", "flower"} and all(v > 0 for v in le0.values())
    for block in results["runs"].values():
        m = np.array(block["m"])
        assert m.shape == (len(toy.QUICK_LAMBDAS), len(toy.QUICK_KAPPAS))
        assert ((m >= 0) & (m <= 1)).all()
        best = block["best"]
        assert best["m"] == pytest.approx(m.max(), abs=1e-4)
        assert best["lambda"] in toy.QUICK_LAMBDAS and best["kappa"] in toy.QUICK_KAPPAS
        for name in le0:  # M_S is max(0, 1 - LE / LE_0) of the reported LE
            expected = max(0.0, 1 - best["le"][name] / le0[name])
            assert best["m_s"][name] == pytest.approx(expected, abs=1e-3)
    # Fig. 4.13: the photometric loss alone ends worse than it started (on Flower here)
    photo = results["photometric"]["best"]
    assert photo["le"]["flower"] > le0["flower"] and photo["m"] == 0.0
    table = (out / TABLE_MD).read_text()
    assert "| diffusion | ODM off: ours (thesis)" in table and "(0.67)" in table
    for png in ("heatmaps_odm-off.png", "heatmaps_odm-on.png", "flower_odm-on.png",
                "horizon_odm-off.png", "flower_diffusion_odm.png", "le_curves.png"):  # fmt: skip
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    depths = np.load(out / "depths.npz")
    assert depths["diffusion/odm-on/flower"].shape == (RES, RES)


@pytest.mark.render
def test_an_interrupted_study_resumed_writes_the_uninterrupted_outputs(
    toy_data, quick_study, tmp_path, monkeypatch
):
    """Ctrl-C in the 3rd run of a `--quick` study keeps its first 2 runs; a new study in that
    folder is refused unless --resume (of the same settings) continues it; the resumed study's
    results.json (timings apart), table.md, depths.npz and figures are the uninterrupted ones."""
    out = tmp_path / "study"
    data = ("--flower", toy_data["flower"], "--horizon", toy_data["horizon"], "--out", out)
    with pytest.raises(UserError, match="^--resume: '.*' holds no unfinished toy study$"):
        _invoke(*data, "--quick", "--quiet", "--resume")
    optimise, calls = toy.optimise, []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return optimise(*args, **kwargs)

    monkeypatch.setattr(toy, "optimise", interrupted)
    with pytest.raises(click.exceptions.Abort):  # what click makes of Ctrl-C
        _invoke(*data, "--quick", "--quiet")
    monkeypatch.undo()
    assert toy_runs.finished(out) == ["photometric", "tv/odm-off"]
    assert not (out / RESULTS_JSON).exists()
    with pytest.raises(UserError, match="^--out: .* unfinished toy study .*add --resume"):
        _invoke(*data, "--quick", "--quiet")
    with pytest.raises(
        UserError, match=r"^--resume: .* other settings \(--iterations 20, now 21\)$"
    ):
        _invoke(*data, "--quick", "--quiet", "--resume", "--iterations", 21)
    _invoke(*data, "--quick", "--quiet", "--resume")
    assert not toy_runs.folder(out).exists()
    whole = json.loads((quick_study / RESULTS_JSON).read_text())
    resumed = json.loads((out / RESULTS_JSON).read_text())
    assert json.dumps(_untimed(resumed)) == json.dumps(_untimed(whole))
    assert resumed["runs"]["diffusion/odm-on"]["seconds"] > 0
    with np.load(quick_study / DEPTHS_NPZ) as a, np.load(out / DEPTHS_NPZ) as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    names = sorted(p.name for p in quick_study.iterdir())
    assert names == sorted(p.name for p in out.iterdir())
    for name in names:  # table.md and the figures, byte for byte
        if name not in (RESULTS_JSON, DEPTHS_NPZ):
            assert (out / name).read_bytes() == (quick_study / name).read_bytes(), name


@pytest.mark.render
def test_jobs_write_the_study_of_one_process(toy_data, quick_study, tmp_path):
    """`--quick --jobs 2`: the same results.json (timings apart), depths.npz and table.md as
    the study run in one process; --jobs with --threads > 1 is one line naming --jobs."""
    data = ("--flower", toy_data["flower"], "--horizon", toy_data["horizon"])
    out = tmp_path / "jobs"
    _invoke(*data, "--out", out, "--quick", "--quiet", "--jobs", 2)
    whole = json.loads((quick_study / RESULTS_JSON).read_text())
    assert json.dumps(_untimed(json.loads((out / RESULTS_JSON).read_text()))) == json.dumps(
        _untimed(whole)
    )
    assert (out / TABLE_MD).read_text() == (quick_study / TABLE_MD).read_text()
    with np.load(quick_study / DEPTHS_NPZ) as a, np.load(out / DEPTHS_NPZ) as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    with pytest.raises(UserError, match="^--jobs: .*--threads 2$"):
        _invoke(*data, "--out", tmp_path / "x", "--quick", "--jobs", 2, "--threads", 2)


@pytest.mark.render
def test_halves_kept_and_combined_through_the_cli_write_the_whole_study(
    toy_data, quick_study, tmp_path
):
    """Two `--quick` studies of three losses each with --keep-runs, their run files copied into
    one folder, then --resume with every loss: the whole study's results.json (timings apart),
    depths.npz and table.md; without --keep-runs the run files go (the other tests)."""
    data = ("--flower", toy_data["flower"], "--horizon", toy_data["horizon"])
    halves = ("tv,tvv,diffusion", "gradient_diffusion,robust_diffusion,robust_gradient_diffusion")
    full = tmp_path / "full"
    for i, losses in enumerate(halves):
        out = tmp_path / f"half{i}"
        _invoke(*data, "--out", out, "--quick", "--quiet", "--losses", losses, "--keep-runs")
        assert len(toy_runs.finished(out)) == 7 and (out / RESULTS_JSON).exists()
        shutil.copytree(toy_runs.folder(out), toy_runs.folder(full), dirs_exist_ok=True)
    _invoke(*data, "--out", full, "--quick", "--quiet", "--resume")
    whole = json.loads((quick_study / RESULTS_JSON).read_text())
    combined = json.loads((full / RESULTS_JSON).read_text())
    assert json.dumps(_untimed(combined)) == json.dumps(_untimed(whole))
    assert (full / TABLE_MD).read_text() == (quick_study / TABLE_MD).read_text()
    with np.load(quick_study / DEPTHS_NPZ) as a, np.load(full / DEPTHS_NPZ) as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    assert not toy_runs.folder(full).exists()


@pytest.mark.render
def test_true_depth_explains_the_frames_better_than_the_start(scenes):
    """Warped with the true depth (ODM on), the references match the centre frame far better
    than with the start depth, and better than with a depth off by 50 %; what is left is the
    renders' own resampling difference (L1 ~0.035 at 200 px, ~0.06 at 64 px: the frames are
    anti-aliased, so a photo texture does not warp exactly)."""
    p = toy.Problem(scenes, torch.zeros(1), torch.zeros(1))
    truth = p.truth.clamp(0.1, 100)
    loss = {}
    for name, d in (
        ("truth", truth),
        ("start", torch.full_like(truth, 10.0)),
        ("off", truth * 1.5),
    ):
        loss[name] = p.photometric(d, p.occlusions(d))
    assert (loss["truth"] < 0.8 * loss["start"]).all(), loss
    assert (loss["truth"] < 0.9 * loss["off"]).all(), loss


@pytest.mark.render
def test_a_grid_point_in_the_batch_follows_its_own_trajectory(scenes):
    """Losses per sample, summed, and Adam element-wise: the batch changes nothing."""
    lam, kap = torch.tensor([0.1, 30.0]), torch.tensor([1.0, 0.3])
    batch = toy.optimise(toy.Problem(scenes, lam, kap), "gradient_diffusion", 8, odm_every=3)
    for g in range(2):
        alone = toy.Problem(scenes, lam[g : g + 1], kap[g : g + 1])
        one = toy.optimise(alone, "gradient_diffusion", 8, odm_every=3)
        for s in range(len(scenes)):
            torch.testing.assert_close(batch.depth[s * 2 + g], one.depth[s], atol=1e-4, rtol=0)
            assert batch.le[s * 2 + g] == pytest.approx(one.le[s], abs=1e-5)
    assert not torch.equal(batch.depth[0], batch.depth[1])  # the two points differ

"""Where a run's time goes (stillbox_gen.phases): the table's arithmetic on made-up times, then
real tiny renders: every worker phase timed, non-negative and within its scene's time, Cycles'
parts (``WorkerSetup.profile``) summing to its whole, the same files with and without that
split, and ``stillbox-gen bench --profile`` printing a row per phase. No timing is asserted
beyond signs and sums."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from conftest import invoke_cli

from stillbox_gen import config, phases, scene, workers
from stillbox_gen.worker_setup import worker_setup

# the phases every scene call of a worker times (the first one of a process also "startup")
IN_SCENE = [
    p.name
    for p in phases.PHASES
    if p.process == phases.WORKER and not (p.derived or p.detail) and p.name != "startup"
]
TOLERANCE = 1e-9  # seconds: sums of float differences of one clock


def test_phase_names_are_unique_and_cycles_parts_are_the_detail_rows():
    names = [p.name for p in phases.PHASES]
    assert len(names) == len(set(names))
    assert phases.CYCLES_PARTS == ("cycles_sync", "cycles_sampling", "cycles_result")
    with pytest.raises(KeyError):
        phases.PhaseTimes().add("sampling", 1.0, 1.0)  # not a phase name


def test_rows_derive_the_rest_and_shares_add_up():
    """2 workers, 10 frames in 2 s; the workers' scene calls took 1.5 s each, of which 1.2 s
    timed; the driver timed 1.5 s of its 2 s."""
    profile = phases.RunProfile()
    for pid, startup in ((1, 0.25), (2, 0.25)):
        profile.add_scene(
            {
                "phases": {"startup": [startup, 0.2], "build": [0.2, 0.2], "cycles": [1.0, 1.9]},
                "seconds": 1.5,
                "cpu_seconds": 2.4,
                "process_cpu_seconds": 2.7,
                "pid": pid,
            }
        )
    profile.times.add("wait", 1.4, 0.0)
    profile.times.add("hash", 0.1, 0.1)
    rows = {r.phase.name: r for r in phases.profile_rows(profile, 10, 2.0, 2, 0.3)}
    assert "cycles_sampling" not in rows  # detail rows only when timed
    assert rows["worker_python"].wall_ms == pytest.approx(1000 * 2 * (1.5 - 1.2) / 10)
    assert rows["worker_outside"].wall_ms == pytest.approx(1000 * (2 * 2.0 - 0.5 - 3.0) / 10)
    assert rows["worker_outside"].cpu_ms == pytest.approx(1000 * 2 * (2.7 - 0.2 - 2.4) / 10)
    assert rows["driver_python"].wall_ms == pytest.approx(1000 * 0.5 / 10)
    for process in (phases.WORKER, phases.DRIVER):
        shares = [r.wall_share for r in rows.values() if r.phase.process == process]
        assert sum(shares) == pytest.approx(1.0)
    assert sum(r.cpu_share for r in rows.values()) == pytest.approx(1.0)
    table = phases.profile_table(profile, 10, 2.0, 2, 0.3, cores=2)
    assert "| cycles | worker |" in table and "| wait | driver |" in table
    assert table.splitlines()[-1].startswith("CPU: 570.00 ms/frame used")


def _cfg(frames: int = 3) -> config.DatasetConfig:
    """The stillbox preset at 16 px, ``frames`` frames a scene."""
    camera = {"width": 16, "height": 16, "frames": frames}
    return config.replace(config.load_preset("stillbox"), camera=camera)


def _spec(frames: int, index: int) -> dict:
    return scene.sample_scene(_cfg(frames), index).to_dict()


def _render(tmp: Path, profile: bool) -> list[dict]:
    """Scene 0 (3 frames) then scene 1 (1 frame) in one worker process with one Cycles thread;
    returns their statistics. Files go to tmp/0 and tmp/1."""
    setup = worker_setup(_cfg(), threads=1, profile=profile)
    with workers.process_pool(1, setup) as pool:
        return [
            pool.submit(workers.render_scene, _spec(n, k), str(tmp / str(k)), "png", False).result()
            for k, n in ((0, 3), (1, 1))
        ]


def _hashes(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> dict[bool, tuple[Path, list[dict]]]:
    """{profile: (folder, statistics)} of the same two scenes with and without Cycles' split."""
    out = {}
    for profile in (True, False):
        tmp = tmp_path_factory.mktemp(f"profile-{profile}")
        out[profile] = (tmp, _render(tmp, profile))
    return out


@pytest.mark.render
@pytest.mark.parametrize("profile", [True, False])
def test_every_worker_phase_is_timed_within_its_scene(rendered, profile):
    _, stats = rendered[profile]
    for i, s in enumerate(stats):
        timed = s["phases"]
        assert set(IN_SCENE) <= set(timed), sorted(timed)
        assert ("startup" in timed) == (i == 0)  # once per worker process
        assert all(wall >= 0 and cpu >= 0 for wall, cpu in timed.values()), timed
        assert timed["cycles"][0] > 0 and timed["build"][0] > 0
        assert sum(timed[k][0] for k in IN_SCENE) <= s["seconds"] + TOLERANCE
        assert sum(timed[k][1] for k in IN_SCENE) <= s["cpu_seconds"] + TOLERANCE
        assert s["build_seconds"] == timed["build"][0]
        assert 0 < s["cpu_seconds"] <= s["process_cpu_seconds"]
        parts = [timed.get(k) for k in phases.CYCLES_PARTS]
        if profile:
            assert all(p is not None and p[0] >= 0 for p in parts), timed
            assert parts[1][0] > 0  # sampling
            for clock in (0, 1):
                assert sum(p[clock] for p in parts) == pytest.approx(timed["cycles"][clock])
        else:
            assert parts == [None, None, None]
    startup_wall, startup_cpu = stats[0]["phases"]["startup"]
    assert startup_wall > 0 and 0 < startup_cpu <= stats[0]["process_cpu_seconds"]


@pytest.mark.render
def test_timing_cycles_apart_changes_no_file(rendered):
    (with_split, _), (without, _) = rendered[True], rendered[False]
    for k in ("0", "1"):
        assert _hashes(with_split / k) == _hashes(without / k)
        assert len(_hashes(with_split / k)) == {"0": 6, "1": 2}[k]  # a PNG and an EXR a frame


@pytest.mark.render
def test_bench_profile_prints_a_row_per_phase(tmp_path):
    result = invoke_cli("bench", "--res", "16:1", "--configs", "fast", "--workers", 1,
                        "--threads", 1, "--psnr-scenes", 1, "--profile")  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    rows = {}
    for line in lines:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 7 and cells[0] in phases.BY_NAME:
            rows[cells[0]] = cells
    assert list(rows) == [p.name for p in phases.PHASES]  # Cycles' parts included, in order
    for process in (phases.WORKER, phases.DRIVER):
        shares = [float(c[4].rstrip(" %")) for c in rows.values()
                  if c[1] == process and not phases.BY_NAME[c[0]].detail]  # fmt: skip
        assert sum(shares) == pytest.approx(100, abs=0.1 * len(shares))
    timed = [c for name, c in rows.items() if not phases.BY_NAME[name].derived]
    assert all(float(c[3]) >= 0 and float(c[5]) >= 0 for c in timed)
    assert any(line.startswith("wall: 10 frames in ") for line in lines)
    assert any(line.startswith("CPU: ") for line in lines)

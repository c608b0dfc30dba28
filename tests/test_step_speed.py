"""benchmark.unsupervised.step_speed: the unsupervised step's levers change no value, and the
measurement runs end to end (its timings are results, not asserted here)."""

from __future__ import annotations

import pytest

from benchmark.unsupervised import step_speed

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("pose,occlusion", [("orientation", False), ("translation", True)])
def test_levers_give_the_same_losses_and_gradients(pose, occlusion):
    rows, check = step_speed.measure(64, 2, 1, pose, occlusion)
    assert [r["variant"] for r in rows] == [
        "supervised",
        "unsupervised",
        "unsupervised, levers off",
    ]
    assert all(r["ms_per_step"] > 0 for r in rows)
    assert check["max_loss_diff"] < 1e-5
    assert check["max_grad_diff"] < 1e-5 * max(1.0, check["max_grad"])


def test_command_writes_its_csv(tmp_path, capsys):
    out = tmp_path / "speed.csv"
    step_speed.main(["--res", "64", "--batch", "2", "--steps", "1", "--out", str(out)])
    lines = out.read_text().splitlines()
    assert lines[0].startswith("variant,px,batch") and len(lines) == 4
    assert "levers on vs off" in capsys.readouterr().out


def test_bad_sizes_are_refused_in_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        step_speed.main(["--res", "100"])
    assert e.value.code == 2 and "--res" in capsys.readouterr().err

"""``diacc plot timespace``: one episode's time-space diagram, from the command line."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np

from diacc.cli import main
from diacc.timespace import Trajectories, speed_profile


def test_speed_profile_averages_active_samples_per_bin():
    traj = Trajectories(
        time_s=np.array([0.0, 1.0]),
        x_m=np.array([[10.0, 30.0], [20.0, 60.0]]),  # (T, V)
        speed_mps=np.array([[4.0, 8.0], [6.0, 100.0]]),
        active=np.array([[True, True], [True, False]]),  # the 100 m/s sample is inactive
        is_cav=np.array([False, True]),
    )
    centres_m, mean_mps = speed_profile(traj, length_m=75.0)
    np.testing.assert_allclose(centres_m, [12.5, 37.5, 62.5])
    np.testing.assert_allclose(mean_mps[:2], [5.0, 8.0])
    assert np.isnan(mean_mps[2])


def test_plot_timespace_command_writes_a_figure(tmp_path, capsys):
    out = tmp_path / "ts"
    args = ["plot", "timespace", "--policy", "pure-hdv", "--map", "train-50"]
    assert main([*args, "--vehicles", "10", "--steps", "15", "--seed", "3", "--out", str(out)]) == 0
    assert "ts.png" in capsys.readouterr().out
    image = mpimg.imread(out.with_suffix(".png"))  # (H, W, 4)
    assert image.shape[1] > image.shape[0] > 300 and float(image[..., :3].std()) > 0.05
    assert out.with_suffix(".pdf").stat().st_size > 0


def test_plot_timespace_rejects_zero_steps(capsys):
    assert main(["plot", "timespace", "--policy", "pure-hdv", "--steps", "0"]) == 2
    assert "diacc: error: --steps must be >= 1, got 0" in capsys.readouterr().err

"""Publishable figures: ``diacc plot timespace`` and speed figures that never pool maps."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest

from diacc.cli import main
from diacc.experiments.evaluate import evaluate
from diacc.experiments.grid import Cell
from diacc.experiments.plots import plot_speeds
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.render import tick_step_m
from diacc.experiments.timespace import Trajectories, speed_profile


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
    assert (
        main([*args, "--vehicles", "10", "--episode-steps", "15", "--seed", "3", "--out", str(out)])
        == 0
    )
    assert "ts.png" in capsys.readouterr().out
    image = mpimg.imread(out.with_suffix(".png"))  # (H, W, 4)
    assert image.shape[1] > image.shape[0] > 300 and float(image[..., :3].std()) > 0.05
    assert out.with_suffix(".pdf").stat().st_size > 0


@pytest.mark.parametrize("flag", ["--episode-steps", "--steps"])  # --steps: the former name
def test_plot_timespace_rejects_zero_steps(capsys, flag):
    assert main(["plot", "timespace", "--policy", "pure-hdv", flag, "0"]) == 2
    err = capsys.readouterr().err
    assert "diacc: error: config key 'episode_steps' must be in [1, 10000], got 0" in err


def test_speed_figures_one_per_map_with_a_caption(tmp_path, monkeypatch):
    cells = [Cell("train-25", 8, 0.25, "D1"), Cell("train-50", 8, 0.25, "D1")]
    evaluate(
        PolicySpec("pure-hdv"),
        cells,
        1,
        tmp_path / "hdv",
        EvalSettings("highway", 20),
        progress=False,
    )
    captions = []
    import diacc.experiments.plots

    real_save = diacc.experiments.plots._save

    def spy(fig, out):
        captions.append(fig.texts[-1].get_text())
        for ax in fig.axes[1:]:  # density panels: labelled, with a legend
            assert ax.get_ylabel() == "density (per m/s)" and ax.get_legend() is not None
        return real_save(fig, out)

    monkeypatch.setattr(diacc.experiments.plots, "_save", spy)
    paths = plot_speeds([tmp_path / "hdv"], tmp_path / "speeds")
    assert [p.name for p in paths] == [
        "speeds-train-25.png",
        "speeds-train-25.pdf",
        "speeds-train-50.png",
        "speeds-train-50.pdf",
    ]
    assert captions[0].startswith(
        "Backend highway, map train-25. Episodes per policy: pure-hdv: 1."
    )
    only = plot_speeds([tmp_path / "hdv"], tmp_path / "one", map_name="train-50")
    assert [p.name for p in only] == ["one.png", "one.pdf"]


def test_tick_step_gives_round_readable_scales():
    assert [tick_step_m(s) for s in (60.0, 150.0, 300.0, 1300.0)] == [10.0, 25.0, 50.0, 250.0]


def test_bottleneck_view_zooms_on_the_lane_drop(tmp_path):
    import diacc
    from diacc.experiments.render import VIEW_SCALE_PX_PER_M, RenderError, render_episode
    from diacc.sim.viewer import Viewer

    env = diacc.parallel_env(map="train-50", scenario={"n_vehicles": 8})
    try:
        env.reset(seed=0)
        road = env.road
        viewer = Viewer(road, env.config.sim, scaling_px_per_m=8.0, view="bottleneck")
        frame = viewer.draw(env.state_)  # (H, W, 3)
    finally:
        env.close()
    left_m, right_m = viewer.window_m
    assert right_m - left_m == pytest.approx(frame.shape[1] / 8.0)
    drop_m = road.segment_starts_m[1]  # train-50: the first reduction starts segment 1
    assert road.segments[1].kind != "multilane"
    assert (drop_m - left_m) / (right_m - left_m) == pytest.approx(0.4)

    cell = Cell("train-50", 8, 0.25, "D1")
    settings = EvalSettings("highway", episode_steps=4)
    spec = PolicySpec("pure-hdv")
    result = render_episode(spec, cell, tmp_path / "b.gif", 4, settings, seed=0, view="bottleneck")
    road_px = (road.max_lanes * road.lane_width_m + 10.0) * VIEW_SCALE_PX_PER_M["bottleneck"]
    assert result.frame_shape[0] > road_px + 60 and result.frame_shape[1] == 1200  # + ruler, text
    with pytest.raises(RenderError, match="unknown --view 'sky'"):
        render_episode(spec, cell, tmp_path / "x.gif", 4, settings, view="sky")

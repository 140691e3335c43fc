"""Figures (training curves, speed distributions) and GIF rendering."""

from __future__ import annotations

import dataclasses
import json

import imageio.v2 as imageio
import numpy as np
import pytest

from diacc.cli import main
from diacc.config import TrainConfig, override
from diacc.experiments.evaluate import evaluate
from diacc.experiments.grid import Cell
from diacc.experiments.plots import PlotError, gaussian_kde, group_curves, read_progress
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.render import RenderError, render_episode

CELL = Cell("train-50", 10, 0.4, "D1")


def _run(
    path, variant: str, seed: int, offset: float, backend: str = "highway", **settings
) -> None:
    """A run directory as ``diacc train`` writes it (config.json, progress.jsonl)."""
    path.mkdir(parents=True)
    values = {"variant": variant, "seed": seed, "env.backend": backend, "run_dir": str(path)}
    cfg = override(TrainConfig(), {**values, **settings})
    (path / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    with open(path / "progress.jsonl", "w") as fh:
        for u in range(1, 11):
            fh.write(
                json.dumps(
                    {
                        "update": u,
                        "global_step": 2000 * u,
                        "global_reward": offset + u,
                        "episode/collision": 1.0 / u,
                        "reward/individual": -offset,
                        "reward/ego_softmin": -offset - u,  # falls as tau anneals
                    }
                )
                + "\n"
            )


def _assert_png(path) -> None:
    image = imageio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert image[..., :3].std() > 5  # not blank


def test_curves_mean_and_band_over_seeds(tmp_path):
    _run(tmp_path / "a1", "diacc", 1, 0.0)
    _run(tmp_path / "a2", "diacc", 2, 2.0)
    _run(tmp_path / "b1", "mappo", 1, 5.0)
    curves = group_curves([tmp_path / "a1", tmp_path / "a2", tmp_path / "b1"], ("global_reward",))
    steps, mean, std = curves["diacc (highway)"]
    assert np.array_equal(steps, 2000.0 * np.arange(1, 11))
    assert np.allclose(mean, np.arange(1, 11) + 1.0) and np.allclose(std, 1.0)
    assert np.allclose(curves["mappo (highway)"][2], 0.0)
    # a run on another backend is its own curve (reproduce's transfer runs), also in
    # a config written before the tree was nested (backend at the top level)
    _run(tmp_path / "s1", "diacc", 1, 9.0, backend="sumo")
    old = tmp_path / "old"
    old.mkdir()
    (old / "config.json").write_text(json.dumps({"variant": "diacc", "backend": "sumo"}))
    (old / "progress.jsonl").write_text((tmp_path / "s1" / "progress.jsonl").read_text())
    curves = group_curves([tmp_path / d for d in ("a1", "a2", "s1", "old")], ("global_reward",))
    assert set(curves) == {"diacc (highway)", "diacc (sumo)"}
    assert np.allclose(curves["diacc (highway)"][1], np.arange(1, 11) + 1.0)
    assert np.allclose(curves["diacc (sumo)"][1], np.arange(1, 11) + 9.0)
    assert (
        main(
            [
                "plot",
                "curves",
                str(tmp_path / "a1"),
                str(tmp_path / "a2"),
                str(tmp_path / "b1"),
                "--out",
                str(tmp_path / "fig" / "curves"),
            ]
        )
        == 0
    )
    _assert_png(tmp_path / "fig" / "curves.png")
    assert (tmp_path / "fig" / "curves.pdf").stat().st_size > 1000


def test_curves_keep_settings_apart_and_plot_the_mean_ego_reward(tmp_path):
    """Runs that differ only in a setting are separate curves (a sweep's); seeds pool."""
    from diacc.experiments.plots import CURVE_PANELS

    dirs = []
    for tau, offset in ((0.05, 0.0), (0.5, 4.0)):
        for seed in (1, 2):
            dirs.append(tmp_path / f"t{tau}-s{seed}")
            _run(dirs[-1], "diacc", seed, offset + seed, **{"env.reward.tau_final": tau})
    curves = group_curves(dirs, CURVE_PANELS["Individual reward"])
    assert set(curves) == {"diacc (highway) tau_final=0.05", "diacc (highway) tau_final=0.5"}
    # the mean ego reward (-offset), not the softmin sum (which falls with every update)
    assert np.allclose(curves["diacc (highway) tau_final=0.05"][1], -1.5)
    assert np.allclose(curves["diacc (highway) tau_final=0.5"][1], -5.5)
    assert np.allclose(curves["diacc (highway) tau_final=0.5"][2], 0.5)  # std over 2 seeds


def test_curves_from_tensorboard(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(tmp_path / "run" / "tb"))
    for step in range(5):
        writer.add_scalar("train/global_reward", float(step), step * 100)
    writer.close()
    series = read_progress(tmp_path / "run")
    assert np.array_equal(series["global_reward"][1], np.arange(5.0))
    with pytest.raises(PlotError, match="neither progress.jsonl nor TensorBoard"):
        (tmp_path / "none").mkdir()
        read_progress(tmp_path / "none")


def test_kde_integrates_to_one():
    grid = np.linspace(-10, 30, 2001)
    density = gaussian_kde(np.random.default_rng(0).normal(10, 2, 500), grid)
    assert np.trapezoid(density, grid) == pytest.approx(1.0, abs=1e-3)


def test_speed_plots(tmp_path):
    for policy in ("pure-hdv", "cooperative"):
        evaluate(
            PolicySpec(policy),
            [CELL],
            1,
            tmp_path / policy,
            EvalSettings("sumo", episode_steps=30),
            progress=False,
        )
    out = tmp_path / "speeds"
    assert (
        main(
            [
                "plot",
                "speeds",
                str(tmp_path / "pure-hdv"),
                str(tmp_path / "cooperative"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    _assert_png(out.with_suffix(".png"))
    assert out.with_suffix(".pdf").stat().st_size > 1000


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_gif_has_expected_frames(tmp_path, backend):
    result = render_episode(
        PolicySpec("pure-hdv"), CELL, tmp_path / "ep.gif", steps=4, settings=EvalSettings(backend)
    )
    frames = imageio.mimread(tmp_path / "ep.gif")
    assert result.n_frames == len(frames) == 5  # the reset state + 4 steps
    first, last = (np.asarray(f)[..., :3].astype(int) for f in (frames[0], frames[-1]))
    assert first.std() > 5 and np.abs(first - last).sum() > 0  # drawn, and vehicles moved
    with pytest.raises(RenderError, match=r"must end in \.gif"):
        render_episode(PolicySpec("pure-hdv"), CELL, tmp_path / "ep.mp4", 4, EvalSettings(backend))


def test_gif_frames_carry_stamp_and_legend(tmp_path):
    from diacc.experiments.render import annotate, step_stamp
    from diacc.sim.viewer import CAV_COLOR, CRASHED_COLOR

    render_episode(
        PolicySpec("pure-hdv"), CELL, tmp_path / "ep.gif", steps=2, settings=EvalSettings()
    )
    frame = np.asarray(imageio.mimread(tmp_path / "ep.gif")[0])[..., :3].astype(int)
    strip = frame[-(2 * 6 + 3 * 17) :]  # two text lines and the legend line
    assert (strip < 60).all(axis=-1).sum() > 200  # black text under the road
    for colour in (CAV_COLOR, CRASHED_COLOR):  # legend swatches
        assert (np.abs(strip - colour).sum(-1) < 30).sum() > 50

    class State:  # a batch of one env: (1,) times, collision rows (env, i, j)
        time_s, step, collisions = np.array([12.0]), np.array([12]), np.array([[0, 3, 7]])

    line, psar = step_stamp(State(), 100, np.array([0, 3, 3, 1, 0]))
    assert line == "t =  12.0 s   step 12/100   crash: vehicles 3+7"
    assert psar == "PSAR this step: cancel_lc x1, force_brake x2"
    assert step_stamp(State(), 100, None)[1] == "PSAR: off for this policy"
    assert annotate(np.zeros((50, 400, 3), np.uint8), ("a", "b")).shape == (50 + 12 + 51, 400, 3)


def test_curve_axes_legends_and_single_seed(tmp_path, monkeypatch):
    from diacc.experiments.plots import _y_limits

    assert _y_limits("Collision rate", 1.0, 1.0) == (-0.03, 1.03)  # a flat 1.00 keeps [0, 1]
    assert _y_limits("Global reward", 1.0, 1.0) == pytest.approx((0.95, 1.05))
    assert _y_limits("Global reward", 0.0, 10.0) == pytest.approx((-0.5, 10.5))
    _run(tmp_path / "a1", "diacc", 1, 0.0)
    _run(tmp_path / "b1", "mappo", 1, 5.0)
    _run(tmp_path / "b2", "mappo", 2, 5.0)
    from diacc.experiments.plots import plot_curves

    captured = {}
    import matplotlib.figure

    original = matplotlib.figure.Figure.savefig

    def spy(fig, *args, **kwargs):
        captured["fig"] = fig
        return original(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)  # keeps the figure to inspect
    paths = plot_curves([tmp_path / d for d in ("a1", "b1", "b2")], tmp_path / "c")
    _assert_png(paths[0])
    axes = captured["fig"].axes
    for ax in axes:  # a legend on every panel, naming the band
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert labels == [
            "diacc (highway): 1 seed, no band",
            "mappo (highway): mean ± std of 2 seeds",
        ]
    assert axes[0].get_ylim() == pytest.approx((-0.03, 1.03))
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(captured["fig"])  # the figure is closed: draw it again
    canvas.draw()
    renderer = canvas.get_renderer()
    for ax in axes:  # step ticks in k, side by side without touching (issue 42)
        ticks = [t for t in ax.get_xticklabels() if t.get_text()]
        boxes = sorted((t.get_window_extent(renderer) for t in ticks), key=lambda b: b.x0)
        assert len(boxes) >= 3 and all(
            a.x1 < b.x0 for a, b in zip(boxes[:-1], boxes[1:], strict=True)
        )
        assert any(t.get_text().endswith("k") for t in ticks)


def test_step_tick_labels_are_short():
    from diacc.experiments.plots import format_steps

    labels = [format_steps(x) for x in (0, 500, 25_000, 200_000, 1_500_000, 3e6)]
    assert labels == ["0", "500", "25k", "200k", "1.5M", "3M"]

"""One episode of any policy as an animated GIF.

Frames come from highway-env's road renderer on both backends: the highway
backend draws itself (``HighwayBackend.render``); a SUMO episode's
:class:`~diacc.state.TrafficState` is drawn by the same renderer on the same
map, so both backends' GIFs look alike. CAVs and the three HDV styles have
distinct colours, and CAVs whose action PSAR changed in the step leading to a
frame are outlined (``highlight``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.evaluate import EpisodeDriver
from diacc.grid import Cell
from diacc.policies import EvalSettings, PolicySpec, build_policy
from diacc.state import TrafficState


class RenderError(ValueError):
    """Bad render request (no steps, wrong output suffix...); one line."""


@dataclass
class RenderResult:
    path: Path
    n_frames: int
    psar_frames: int  # frames with at least one highlighted CAV
    frame_shape: tuple[int, ...]


class _FrameSource:
    """Draws (state, highlight) with highway-env's renderer whatever the backend."""

    def __init__(self, driver: EpisodeDriver) -> None:
        self.driver = driver
        self.own = driver.backend.__class__.__name__ == "HighwayBackend"
        self.renderer = None
        if not self.own:
            from diacc.backends.highway_render import HighwayRenderer
            from diacc.backends.highway_road import build_road_network

            self.renderer = HighwayRenderer(
                driver.road, build_road_network(driver.road), driver.cfg.sim
            )

    def draw(self, state: TrafficState, highlight: np.ndarray) -> np.ndarray:
        if self.own:
            return self.driver.backend.render(highlight=highlight)
        return self.renderer.draw(state, highlight)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()


def render_episode(
    spec: PolicySpec,
    cell: Cell,
    out: str | Path,
    steps: int,
    settings: EvalSettings,
    seed: int | None = None,
    fps: float = 5.0,
) -> RenderResult:
    """Play one episode (at most ``steps`` decisions) and write it as a GIF.

    The seed defaults to the evaluation seed of episode 0 of ``cell``, so the
    GIF shows the first episode ``diacc eval`` runs in that cell.
    """
    import imageio.v2 as imageio

    out = Path(out)
    if out.suffix.lower() != ".gif":
        raise RenderError(f"--out must end in .gif, got {out}")
    if steps < 1:
        raise RenderError(f"--steps must be >= 1, got {steps}")
    if fps <= 0:
        raise RenderError(f"--fps must be > 0, got {fps}")
    policy = build_policy(spec)
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    source = None
    try:
        state = driver.reset(cell.seed(0) if seed is None else seed)
        source = _FrameSource(driver)
        frames = [source.draw(state, np.zeros(state.n_vehicles, bool))]
        psar_frames = 0
        while not driver.done and len(frames) <= steps:
            state = driver.step()
            highlight = driver.psar_rule != 0  # (V,)
            psar_frames += int(highlight.any())
            frames.append(source.draw(state, highlight))
    finally:
        if source is not None:
            source.close()
        driver.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(out, [np.asarray(f, np.uint8) for f in frames], duration=1000.0 / fps, loop=0)
    return RenderResult(out, len(frames), psar_frames, tuple(frames[0].shape))

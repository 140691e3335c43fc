"""One episode of any policy as an animated GIF.

Frames come from :class:`diacc.sim.viewer.Viewer` (highway-env's road renderer),
which draws the :class:`~diacc.sim.state.TrafficState` whichever backend made it,
so both backends' GIFs look alike. CAVs and the three HDV styles have
distinct colours, crashed vehicles are red, and CAVs whose action PSAR changed
in the step leading to a frame are outlined (``highlight``).

Below the road, every frame carries a strip (:func:`annotate`) with a
position scale (metres along the route), the simulated time and decision
step, the PSAR rules that fired in that step and the crash, if any, and a
legend of the colours. ``view="bottleneck"`` keeps the camera on the lane
drop at twice the scale (:data:`VIEW_SCALE_PX_PER_M`), where the queue forms.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, Policy, PolicySpec, build_policy
from diacc.sim.state import TrafficState

#: Pixels per metre of each view: the bottleneck view zooms in (cars ~40 x 16 px).
VIEW_SCALE_PX_PER_M = {"traffic": 4.0, "bottleneck": 8.0}


class RenderError(DiaccError, ValueError):
    """Bad render request (no steps, wrong output suffix...); one line."""


@dataclass
class RenderResult:
    path: Path
    n_frames: int
    psar_frames: int  # frames with at least one highlighted CAV
    frame_shape: tuple[int, ...]


def _legend_entries() -> list[tuple[str, tuple[int, int, int], bool]]:
    """(label, RGB, outline only) of the legend, in the renderer's own colours."""
    from diacc.sim.scenario import STYLE_NAMES
    from diacc.sim.viewer import (
        CAV_COLOR,
        CRASHED_COLOR,
        HIGHLIGHT_COLOR,
        OFFROAD_COLOR,
        STYLE_COLORS,
    )

    entries = [(f"HDV {name}", STYLE_COLORS[code], False) for code, name in enumerate(STYLE_NAMES)]
    return [
        *entries,
        ("CAV", CAV_COLOR, False),
        ("PSAR rule fired", HIGHLIGHT_COLOR, True),
        ("crash", CRASHED_COLOR, False),
        ("closed lane", OFFROAD_COLOR, False),
    ]


def step_stamp(
    state: TrafficState, max_steps: int, psar_rule: np.ndarray | None
) -> tuple[str, str]:
    """(time / step / crash line, PSAR line) under a frame of ``state``, a batch of one env;
    ``psar_rule`` (V,), None: no PSAR."""
    from diacc.envs.psar import RULE_NAMES

    crash = (
        "crash: vehicles " + ", ".join(f"{a}+{b}" for a, b in state.collisions[:, 1:].tolist())
        if len(state.collisions)
        else "no crash"
    )
    line = f"t = {state.time_s[0]:5.1f} s   step {state.step[0]}/{max_steps}   {crash}"
    if psar_rule is None:
        return line, "PSAR: off for this policy"
    counts = np.bincount(np.asarray(psar_rule, np.int64), minlength=len(RULE_NAMES))  # (R,)
    fired = [f"{RULE_NAMES[r]} x{counts[r]}" for r in range(1, len(RULE_NAMES)) if counts[r]]
    return line, "PSAR this step: " + (", ".join(fired) if fired else "no rule fired")


def tick_step_m(span_m: float) -> float:
    """A round tick spacing (10, 25, 50, 100 ... m) giving at most ~8 ticks over ``span_m``."""
    for step in (10.0, 25.0, 50.0, 100.0, 250.0, 500.0):
        if span_m / step <= 8:
            return step
    return 1000.0


def annotate(
    frame: np.ndarray, lines: tuple[str, ...], window_m: tuple[float, float] | None = None
) -> np.ndarray:
    """The frame (H, W, 3) with a strip below: a position scale over ``window_m`` (the
    road positions at the frame's left and right edges), ``lines`` of text, the legend."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=13)
    line_h, pad = 17, 6
    height, width = frame.shape[:2]
    ruler_h = 22 if window_m is not None else 0
    strip_h = pad * 2 + ruler_h + line_h * (len(lines) + 1)
    image = Image.new("RGB", (width, height + strip_h), (255, 255, 255))
    image.paste(Image.fromarray(np.asarray(frame, np.uint8)[..., :3]), (0, 0))
    draw = ImageDraw.Draw(image)
    if window_m is not None:
        left_m, right_m = window_m
        step = tick_step_m(right_m - left_m)
        px_per_m = width / (right_m - left_m)
        draw.line((0, height + 1, width, height + 1), fill=(0, 0, 0), width=1)
        for x_m in np.arange(np.ceil(left_m / step) * step, right_m, step):
            x_px = round((x_m - left_m) * px_per_m)
            draw.line((x_px, height, x_px, height + 6), fill=(0, 0, 0), width=1)
            draw.text((x_px + 2, height + 4), f"{x_m:.0f} m", fill=(0, 0, 0), font=font)
    y = height + pad + ruler_h
    for text in lines:
        draw.text((pad, y), text, fill=(0, 0, 0), font=font)
        y += line_h
    x = pad
    for label, colour, outline in _legend_entries():
        box = (x, y + 3, x + 18, y + 13)
        draw.rectangle(box, outline=colour, width=2) if outline else draw.rectangle(box, colour)
        x += 22
        draw.text((x, y), label, fill=(0, 0, 0), font=font)
        x += int(draw.textlength(label, font=font)) + 14
    return np.asarray(image)


def episode_driver(
    spec: PolicySpec, cell: Cell, steps: int | None, settings: EvalSettings
) -> tuple[Policy, EpisodeDriver]:
    """(policy, driver) of one shown episode of ``cell``: the policy's own environment
    for that cell, ended after at most ``steps`` decisions (GIFs, time-space diagrams;
    None: the episode's own length, ``settings.episode_steps`` or the policy's)."""
    policy = build_policy(spec)
    cfg = policy.env_config(cell, settings)
    own_steps = cfg.sim.episode_steps
    max_steps = own_steps if steps is None else min(steps, own_steps)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, episode_steps=max_steps))
    return policy, EpisodeDriver(policy, cfg)


def render_episode(
    spec: PolicySpec,
    cell: Cell,
    out: str | Path,
    steps: int | None,
    settings: EvalSettings,
    seed: int | None = None,
    fps: float = 5.0,
    view: str = "traffic",
) -> RenderResult:
    """Play one episode (at most ``steps`` decisions; None: all of it) and write it as a GIF.

    The seed defaults to the evaluation seed of episode 0 of ``cell``, so the
    GIF shows the first episode ``diacc eval`` runs in that cell. ``view``:
    follow the traffic, or watch the bottleneck up close (module docstring).
    """
    import imageio.v2 as imageio

    out = Path(out)
    if out.suffix.lower() != ".gif":
        raise RenderError(f"--out must end in .gif, got {out}")
    if steps is not None and steps < 1:
        raise RenderError(f"--steps must be >= 1, got {steps}")
    if fps <= 0:
        raise RenderError(f"--fps must be > 0, got {fps}")
    if view not in VIEW_SCALE_PX_PER_M:
        raise RenderError(f"unknown --view {view!r}; use one of: {', '.join(VIEW_SCALE_PX_PER_M)}")
    from diacc.sim.viewer import Viewer

    _, driver = episode_driver(spec, cell, steps, settings)
    max_steps = driver.cfg.sim.episode_steps  # the GIF's episode ends there
    source = None
    try:
        state = driver.reset(cell.seed(0, settings.stream) if seed is None else seed)
        scale = VIEW_SCALE_PX_PER_M[view]
        road_width_m = driver.road.max_lanes * driver.road.lane_width_m
        source = Viewer(
            driver.road,
            driver.cfg.sim,
            height_px=160 if view == "traffic" else int((road_width_m + 10.0) * scale),
            scaling_px_per_m=scale,
            view=view,
        )
        psar_on = driver.cfg.psar_enabled
        no_rule = np.zeros(state.n_vehicles, np.int8)  # (V,)
        first = source.draw(state, no_rule != 0)
        frames = [
            annotate(
                first,
                step_stamp(state, max_steps, no_rule if psar_on else None),
                source.window_m,
            )
        ]
        psar_frames = 0
        while not driver.done:
            state = driver.step()
            highlight = driver.psar_rule != 0  # (V,)
            psar_frames += int(highlight.any())
            stamp = step_stamp(state, max_steps, driver.psar_rule if psar_on else None)
            frames.append(annotate(source.draw(state, highlight), stamp, source.window_m))
    finally:
        if source is not None:
            source.close()
        driver.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(out, [np.asarray(f, np.uint8) for f in frames], duration=1000.0 / fps, loop=0)
    return RenderResult(out, len(frames), psar_frames, tuple(frames[0].shape))

"""Offscreen frames of any backend's TrafficState, drawn by highway-env's own renderer.

The viewer reads only the :class:`~diacc.sim.state.TrafficState` and the map, so
an episode looks the same whichever simulator produced it (``diacc render``,
``BottleneckEnv.render``). highway-env's viewer opens a display; with SDL's
dummy driver its frames come out black. Here we set the dummy
driver, draw into a plain
``pygame.Surface`` wrapped as highway-env's ``WorldSurface``, and let
``RoadGraphics`` / ``VehicleGraphics`` paint lanes and vehicles. Lightweight
highway-env ``Vehicle`` objects are synced from the arrays only when a frame
is asked for, so rendering costs nothing during training.
"""

from __future__ import annotations

import os
import sys

#: Whether a display could show a window, read before the dummy driver below is set.
_DISPLAY = sys.platform in ("darwin", "win32") or bool(
    os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
)
_DUMMY_SET_HERE = "SDL_VIDEODRIVER" not in os.environ
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import numpy as np  # noqa: E402
import pygame  # noqa: E402
from highway_env.road.graphics import LaneGraphics, RoadGraphics, WorldSurface  # noqa: E402
from highway_env.road.road import Road  # noqa: E402
from highway_env.vehicle.graphics import VehicleGraphics  # noqa: E402
from highway_env.vehicle.kinematics import Vehicle  # noqa: E402

from diacc.sim.backends.highway.road import build_road_network, to_highway_env_y  # noqa: E402
from diacc.sim.maps import Map  # noqa: E402
from diacc.sim.scenario import AGGRESSIVE, CAUTIOUS, NORMAL  # noqa: E402
from diacc.sim.settings import SimConfig  # noqa: E402
from diacc.sim.state import TrafficState  # noqa: E402

#: Vehicle colours (RGB): CAVs green as highway-env's ego, HDVs by style.
CAV_COLOR = VehicleGraphics.EGO_COLOR
#: Where the camera looks: at the mean position of the traffic, or at the bottleneck.
VIEWS = ("traffic", "bottleneck")
STYLE_COLORS = {
    AGGRESSIVE: (255, 120, 60),
    NORMAL: VehicleGraphics.BLUE,
    CAUTIOUS: VehicleGraphics.YELLOW,
}
CRASHED_COLOR = (200, 0, 0)
HIGHLIGHT_COLOR = (255, 0, 255)
#: Lanes that do not exist in a segment (the lane drop): a sandy hatch, far from every
#: vehicle colour (a green verge read as a row of CAVs).
OFFROAD_COLOR = (196, 182, 150)
OFFROAD_HATCH_COLOR = (170, 155, 120)


class Viewer:
    """Draws a :class:`TrafficState` of one map; one pygame surface reused per frame."""

    def __init__(
        self,
        road: Map,
        sim: SimConfig,
        width_px: int = 1200,
        height_px: int = 160,
        scaling_px_per_m: float = 4.0,
        view: str = "traffic",
    ) -> None:
        """``view``: ``"traffic"`` centres each frame on the mean position of the
        vehicles; ``"bottleneck"`` keeps the camera still on the first lane drop,
        with the last 40 % of the window after it (where the queue forms)."""
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; use one of: {', '.join(VIEWS)}")
        self.road_map = road
        self.sim = sim
        self.view = view
        self.window_m = (0.0, 0.0)  # (left, right) road positions of the last frame
        self.road = Road(network=build_road_network(road), vehicles=[], record_history=False)
        self.surface = WorldSurface((width_px, height_px), 0, pygame.Surface((width_px, height_px)))
        self.surface.scaling = scaling_px_per_m
        self._vehicles: list[Vehicle] = []

    def _sync(self, state: TrafficState) -> None:
        """Mirror the arrays into highway-env Vehicle objects (render time only)."""
        n = state.n_vehicles
        while len(self._vehicles) < n:
            vehicle = Vehicle(self.road, [0.0, 0.0])
            vehicle.LENGTH = self.sim.vehicle_length_m
            vehicle.WIDTH = self.sim.vehicle_width_m
            self._vehicles.append(vehicle)
        y_he = to_highway_env_y(self.road_map, state.y_m[0])
        crashed = np.zeros(n, dtype=bool)
        crashed[state.collisions[:, 1:].reshape(-1)] = True  # rows (0, i, j)
        shown = []
        for i in np.flatnonzero(state.active[0]):  # render path only, not the simulation
            vehicle = self._vehicles[i]
            vehicle.position = np.array([state.x_m[0][i], y_he[i]])
            vehicle.heading = -float(state.heading_rad[0][i])  # screen y points down
            vehicle.speed = float(state.speed_mps[0][i])
            if crashed[i]:
                vehicle.color = CRASHED_COLOR
            elif state.is_cav[0][i]:
                vehicle.color = CAV_COLOR
            else:
                vehicle.color = STYLE_COLORS[int(state.style[0][i])]
            shown.append(vehicle)
        self.road.vehicles = shown

    def draw(self, state: TrafficState, highlight: np.ndarray | None = None) -> np.ndarray:
        """(H, W, 3) uint8 frame centred on the active traffic of ``state``, a batch of one env."""
        if state.n_envs != 1:
            raise ValueError(f"the viewer draws one env, got a batch of {state.n_envs}")
        if highlight is not None:
            highlight = np.asarray(highlight, dtype=bool)
            if highlight.shape != (state.n_vehicles,):
                raise ValueError(
                    f"highlight must have shape ({state.n_vehicles},), got {highlight.shape}"
                )
        self._sync(state)
        surface = self.surface
        centre_x = self._centre_m(state)
        road_mid_y = float(
            to_highway_env_y(
                self.road_map, 0.5 * self.road_map.max_lanes * self.road_map.lane_width_m
            )
        )
        surface.move_display_window_to(np.array([centre_x, road_mid_y]))
        surface.fill(surface.GREY)
        self._draw_offroad()  # under the lane lines, so they stay visible
        for lanes in (ls for to in self.road.network.graph.values() for ls in to.values()):
            for lane in lanes:
                LaneGraphics.display(lane, surface)
        RoadGraphics.display_traffic(self.road, surface, offscreen=True)
        if highlight is not None:
            self._draw_outlines(state, highlight)
        half_width_m = surface.get_width() / surface.scaling / 2
        self.window_m = (centre_x - half_width_m, centre_x + half_width_m)
        frame = pygame.surfarray.array3d(surface)  # (W, H, 3)
        return np.ascontiguousarray(np.transpose(frame, (1, 0, 2))).astype(np.uint8)

    def _centre_m(self, state: TrafficState) -> float:
        if self.view == "bottleneck":
            road = self.road_map
            drops = [
                start
                for seg, start in zip(road.segments, road.segment_starts_m, strict=True)
                if seg.kind != "multilane"
            ]
            width_m = self.surface.get_width() / self.surface.scaling
            drop_m = drops[0] if drops else 0.5 * road.length_m
            return float(drop_m + 0.1 * width_m)  # the drop at 40 % of the width
        return float(state.x_m[0][state.active[0]].mean()) if state.active[0].any() else 0.0

    def _draw_offroad(self) -> None:
        """Paint lanes that do not exist in a segment (the bottleneck) as verge."""
        road, surface = self.road_map, self.surface
        exists = road.lane_exists()
        starts, ends = road.segment_starts_m, road.segment_ends_m
        for s in range(len(road.segments)):
            for lane in np.flatnonzero(~exists[s]):
                y_top = float(to_highway_env_y(road, (lane + 1) * road.lane_width_m))
                x0, y0 = surface.pos2pix(starts[s], y_top)
                width_px, height_px = (
                    surface.pix(ends[s] - starts[s]),
                    surface.pix(road.lane_width_m),
                )
                pygame.draw.rect(surface, OFFROAD_COLOR, (x0, y0, width_px, height_px), 0)
                for dx in range(0, width_px + height_px, 12):  # diagonal hatch
                    start = (x0 + dx, y0)
                    end = (x0 + dx - height_px, y0 + height_px)
                    clipped = pygame.Rect(x0, y0, width_px, height_px).clipline(start, end)
                    if clipped:
                        pygame.draw.line(surface, OFFROAD_HATCH_COLOR, *clipped, 2)

    def _draw_outlines(self, state: TrafficState, highlight: np.ndarray) -> None:
        half_l, half_w = 0.5 * self.sim.vehicle_length_m + 0.6, 0.5 * self.sim.vehicle_width_m + 0.6
        y_he = to_highway_env_y(self.road_map, state.y_m[0])
        for i in np.flatnonzero(highlight & state.active[0]):
            h = -float(state.heading_rad[0][i])
            c, s = np.cos(h), np.sin(h)
            corners = [
                (state.x_m[0][i] + c * dl - s * dw, y_he[i] + s * dl + c * dw)
                for dl, dw in (
                    (half_l, half_w),
                    (half_l, -half_w),
                    (-half_l, -half_w),
                    (-half_l, half_w),
                )
            ]
            pixels = [self.surface.pos2pix(px, py) for px, py in corners]
            pygame.draw.polygon(self.surface, HIGHLIGHT_COLOR, pixels, 2)

    def close(self) -> None:
        self._vehicles.clear()
        self.road.vehicles = []


def display_available() -> bool:
    """Whether a window can be shown (a display, and no video driver forced to ``dummy``)."""
    return _DISPLAY and (_DUMMY_SET_HERE or os.environ.get("SDL_VIDEODRIVER") != "dummy")


class Window:
    """A pygame window showing the viewer's frames (``render_mode="human"``).

    Frames are drawn offscreen (:class:`Viewer`) and blitted here, so the
    window shows exactly what ``rgb_array`` returns. The dummy video driver
    this module sets for offscreen drawing is lifted before the display starts.
    """

    def __init__(self, title: str) -> None:
        if _DUMMY_SET_HERE and os.environ.get("SDL_VIDEODRIVER") == "dummy":
            del os.environ["SDL_VIDEODRIVER"]
        pygame.display.init()
        pygame.display.set_caption(title)
        self._screen: pygame.Surface | None = None

    def show(self, frame: np.ndarray) -> None:
        """Show one (H, W, 3) uint8 frame; keeps the window responsive."""
        height_px, width_px = frame.shape[:2]
        if self._screen is None or self._screen.get_size() != (width_px, height_px):
            self._screen = pygame.display.set_mode((width_px, height_px))
        pygame.surfarray.blit_array(self._screen, np.transpose(frame, (1, 0, 2)))
        pygame.display.flip()
        pygame.event.pump()

    def close(self) -> None:
        pygame.display.quit()

"""Time the observation builder per decision step: push + actor (all CAVs) + critic.

States are random but valid (vehicles spread over the route in existing
lanes, 10 % inactive), so the numbers do not depend on a simulator.

    python benchmarks/speed/observation_build.py [--steps 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diacc.config import CAV_STYLE, ObservationConfig
from diacc.envs.observation import ObservationBuilder
from diacc.sim.maps import Map, load_map
from diacc.sim.state import TrafficState


def random_state(
    road: Map, n: int, n_cav: int, rng: np.random.Generator, step: int
) -> TrafficState:
    """A valid TrafficState with n vehicles, the first n_cav of them CAVs."""
    x = rng.uniform(0.0, road.length_m, n)
    seg = road.segment_of(x)
    first = np.array([road.first_lane(s) for s in seg])
    n_lanes = np.array([road.segments[s].lanes for s in seg])
    lane = (first + rng.integers(0, 1 << 20, n) % n_lanes).astype(np.int16)
    is_cav = np.arange(n) < n_cav
    active = rng.random(n) > 0.1
    return TrafficState(
        time_s=float(step),
        step=step,
        vehicle_id=np.arange(n, dtype=np.int32),
        x_m=x,
        y_m=road.lane_center_y_m(lane).astype(np.float64),
        speed_mps=rng.uniform(0.0, 25.0, n),
        accel_mps2=np.zeros(n),
        heading_rad=rng.normal(0.0, 0.05, n),
        lane=lane,
        segment=seg.astype(np.int16),
        length_m=np.full(n, 5.0),
        width_m=np.full(n, 1.8),
        is_cav=is_cav,
        style=np.where(is_cav, CAV_STYLE, 1).astype(np.int8),
        active=active,
        arrived=np.zeros(n, bool),
        collisions=np.zeros((0, 2), np.int32),
        arrivals=np.zeros(0, np.int32),
    )


def time_per_step_ms(road: Map, n: int, n_cav: int, steps: int, seed: int = 0) -> float:
    rng = np.random.default_rng(seed)
    states = [random_state(road, n, n_cav, rng, t) for t in range(steps + 1)]
    builder = ObservationBuilder(road, ObservationConfig(), episode_steps=steps)
    cav_index = np.arange(n_cav)
    memory = np.zeros((n_cav, 2), np.int64)
    refined = np.zeros(n, np.int64)
    builder.reset(states[0])
    start = time.perf_counter()
    for state in states[1:]:
        builder.push(state)
        builder.actor(cav_index, memory, refined)
        builder.critic()
    return (time.perf_counter() - start) / steps * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--map", default="train-25")
    args = parser.parse_args()
    road = load_map(args.map)
    for n, n_cav in ((25, 10), (40, 16)):
        ms = time_per_step_ms(road, n, n_cav, args.steps)
        print(f"N = {n:2d}, CAVs = {n_cav:2d}: {ms:.3f} ms/step (push + actor + critic)")


if __name__ == "__main__":
    main()

"""Which greedy action a policy picks in which situation (issue 58, item 5).

    python benchmarks/studies/nopsar-learning/situation_probe.py POLICY [POLICY ...] \
        [--backend highway|sumo] [--episodes 10] [--episode-steps 330] [--map train-50]

Plays ``validation`` episodes of the training cell (``train-50``, N = 25, 40 % CAVs,
D1, ``realistic``; ``--map`` another road with that traffic, e.g. a generated
``gen-validation-17``) with each policy (anything ``diacc eval --policy`` takes), greedy,
and files every living CAV's decision under the situation it was taken in, read
from the traffic state before the step:

* **following**: the time gap to the vehicle ahead in the CAV's lane (bumper to
  bumper over the CAV's speed): none within 100 m, >= 2 s, 1-2 s, < 1 s; and whether
  the CAV closes in on it (more than 2 m/s faster);
* **lane**: whether the CAV's lane ends ahead, and how far away (< 300 m, 300 m or
  more), or does not end.

Prints, per policy and situation, the share of decisions taken there and the share of
each action among them (the policy's own choice, before PSAR where it has PSAR): what
``action_probe.py``'s one line per run sums over. Why: a no-PSAR agent that brakes on
4-8 % of its decisions should brake where a gap closes, not at random.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter

import numpy as np
import torch

from diacc.envs.actions import ACTION_NAMES
from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy
from diacc.sim.state import TrafficState

#: The training cell's traffic; ``--map`` puts it on another road.
CELL = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")
LOOK_AHEAD_M = 100.0
CLOSING_MPS = 2.0
NEAR_END_M = 300.0
#: The situations in the order the table lists them, from the easiest to the tightest.
SITUATIONS = {
    "following": [
        "no vehicle within 100 m",
        *(f"gap {band}, {how}" for band in (">= 2 s", "1-2 s", "< 1 s")
          for how in ("not closing in", "closing in")),
    ],
    "lane": ["its lane does not end", "its lane ends >= 300 m ahead",
             "its lane ends < 300 m ahead"],
}  # fmt: skip


class Recording:
    """The policy, with its last ``act``'s actions and living slots kept for the probe."""

    def __init__(self, policy) -> None:
        self.policy = policy
        self.last: np.ndarray | None = None
        self.alive: np.ndarray | None = None  # (C,) slots with a CAV on the road

    def __getattr__(self, name: str):  # everything else is the policy's
        return getattr(self.policy, name)

    def act(self, actor_obs, first_step):
        self.alive = actor_obs.alive.copy()
        self.last = np.asarray(self.policy.act(actor_obs, first_step=first_step))  # (C,)
        return self.last


def following(state: TrafficState, v: int) -> str:
    """The time gap to vehicle ``v``'s leader in its lane, and whether ``v`` closes in."""
    x, lane = state.x_m[0], state.lane[0]  # (V,)
    ahead = state.active[0] & (lane == lane[v]) & (x > x[v])  # (V,)
    ahead[v] = False
    if not ahead.any():
        return SITUATIONS["following"][0]
    lead = int(np.flatnonzero(ahead)[np.argmin(x[ahead])])
    gap_m = x[lead] - x[v] - 0.5 * (state.length_m[0, lead] + state.length_m[0, v])
    if gap_m > LOOK_AHEAD_M:
        return SITUATIONS["following"][0]
    speed = state.speed_mps[0]
    gap_s = gap_m / max(speed[v], 0.1)
    band = ">= 2 s" if gap_s >= 2 else ("1-2 s" if gap_s >= 1 else "< 1 s")
    closing = speed[v] - speed[lead] > CLOSING_MPS
    return f"gap {band}, {'closing in' if closing else 'not closing in'}"


def lane_end(state: TrafficState, v: int, lane_end_m: np.ndarray) -> str:
    """How far ahead vehicle ``v``'s lane ends (``lane_end_m`` (S, L): inf if it does not)."""
    to_end_m = lane_end_m[state.segment[0, v], state.lane[0, v]] - state.x_m[0, v]
    if not np.isfinite(to_end_m):
        return SITUATIONS["lane"][0]
    return SITUATIONS["lane"][2 if to_end_m < NEAR_END_M else 1]


def probe(
    policy_name: str, backend: str, episodes: int, episode_steps: int, cell: Cell = CELL
) -> Counter:
    """Counter of (situation kind, situation, action) over every living CAV's decision."""
    policy = Recording(build_policy(parse_policy(policy_name)))
    settings = EvalSettings(backend=backend, episode_steps=episode_steps, style_preset="realistic")
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    lane_end_m = driver.road.lane_end_m()  # (S, L)
    counts: Counter = Counter()
    try:
        for episode in range(episodes):
            driver.reset(cell.seed(episode, "validation"))
            while not driver.done:
                cavs = driver.env.cav_index.copy()  # (C,) the slots' vehicles
                state = driver.state  # before the step: the situation the decision met
                driver.step()
                for slot in np.flatnonzero(policy.alive):
                    v, action = int(cavs[slot]), ACTION_NAMES[int(policy.last[slot])]
                    counts["following", following(state, v), action] += 1
                    counts["lane", lane_end(state, v, lane_end_m), action] += 1
    finally:
        driver.close()
    return counts


def table(name: str, backend: str, counts: Counter) -> str:
    lines = [
        f"\n{name} on {backend}:\n",
        "| situation | decisions | " + " | ".join(ACTION_NAMES) + " |",
        "|---|---|" + "---|" * len(ACTION_NAMES),
    ]
    for kind in ("following", "lane"):
        total = sum(n for (k, _, _), n in counts.items() if k == kind)
        for situation in SITUATIONS[kind]:
            row = [counts[kind, situation, a] for a in ACTION_NAMES]
            if not sum(row):
                continue
            shares = " | ".join(f"{n / sum(row):.0%}" for n in row)
            lines.append(f"| {situation} | {sum(row) / total:.0%} | {shares} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policies", nargs="+")
    parser.add_argument("--backend", default="highway", choices=("highway", "sumo"))
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--episode-steps", type=int, default=330)
    parser.add_argument("--map", default=CELL.map, help="the road (default: train-50)")
    args = parser.parse_args()
    cell = dataclasses.replace(CELL, map=args.map)
    torch.set_num_threads(1)
    for name in args.policies:
        try:
            counts = probe(name, args.backend, args.episodes, args.episode_steps, cell)
        except DiaccError as error:  # no checkpoint there, or an unusable one: one line
            raise SystemExit(f"situation_probe.py: error: {error}") from None
        print(table(f"{name.rstrip('/').split('/')[-1]} ({cell.map})", args.backend, counts))


if __name__ == "__main__":
    main()

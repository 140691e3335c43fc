"""Does the actor's choice depend on what it sees? Checkpoints' logits on the same
decisions of a few `validation` episodes.

    python benchmarks/studies/suite-training/logit_probe.py CHECKPOINT [CHECKPOINT ...] \
        [--episodes 3] [--map train-50] [--driver heuristic]

One policy drives (``--driver``, the heuristic by default, so that every checkpoint is
read on the same traffic and none on the queue its own collapse would cause); every
checkpoint is fed the same observations of every living CAV (its own GRU memory) and
its actor's logits, encoder features and GRU state are recorded. Prints per checkpoint
and action the mean logit and its spread across decisions, how often each action is the
argmax, the margin between the two most likely actions (a margin whose mean dwarfs its
spread is a choice made before looking: one greedy action everywhere, issue 58's
"collapse"), and how much the encoder and GRU units move across decisions.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from diacc.envs.actions import ACTION_NAMES
from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy

#: A unit whose standard deviation across decisions is below this barely moves.
STILL = 1e-2


class Probe:
    """A checkpoint fed the driver's observations; keeps what its actor computes for
    living CAVs: logits (D, A), encoder features (D, E), GRU state (D, H)."""

    def __init__(self, name: str) -> None:
        self.name, self.policy = name, build_policy(parse_policy(name))
        self.rows: dict[str, list[np.ndarray]] = {"logits": [], "features": [], "gru": []}
        self._last: dict[str, np.ndarray] = {}
        actor = self.policy.actor
        actor.encoder.register_forward_hook(self._keep_features)
        actor.head.register_forward_hook(self._keep_head)

    def _keep_features(self, _module, _inputs, out) -> None:
        self._last["features"] = out.detach().numpy().copy()

    def _keep_head(self, _module, inputs, out) -> None:  # the head reads the GRU state
        self._last["gru"] = inputs[0].detach().numpy().copy()
        self._last["logits"] = out.detach().numpy().copy()

    def read(self, actor_obs, first_step) -> None:
        if actor_obs.alive.shape[0] == 0:
            return
        self.policy.act(actor_obs, first_step)
        alive = np.asarray(actor_obs.alive, bool)  # (C,)
        for key, rows in self.rows.items():
            rows.append(self._last[key][alive])


class ProbingDriver:
    """The driving policy, with every probe reading each decision's observations."""

    def __init__(self, driver, probes: list[Probe]) -> None:
        self.driver, self.probes = driver, probes
        self.label = driver.label

    def __getattr__(self, name):  # env_config, describe, ... are the driver's
        return getattr(self.driver, name)

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        self.driver.begin_episode(n_cavs, seed)
        for probe in self.probes:
            probe.policy.begin_episode(n_cavs, seed)

    def act(self, actor_obs, first_step):
        for probe in self.probes:
            probe.read(actor_obs, first_step)
        return self.driver.act(actor_obs, first_step)


def report(probe: Probe) -> None:
    logits = np.concatenate(probe.rows["logits"])  # (D, A)
    print(f"{probe.name}: {len(logits)} decisions")
    top = logits.argmax(1)  # (D,)
    for a, name in enumerate(ACTION_NAMES):
        print(
            f"  {name:10s} logit mean {logits[:, a].mean():+6.2f}  sd {logits[:, a].std():5.2f}"
            f"  argmax on {np.mean(top == a):6.1%}"
        )
    first, second = np.argsort(logits.mean(0))[::-1][:2]
    margin = logits[:, first] - logits[:, second]  # (D,)
    print(
        f"  margin {ACTION_NAMES[first]} - {ACTION_NAMES[second]}: mean {margin.mean():+.2f}, "
        f"sd {margin.std():.2f} across decisions "
        f"(|mean| / sd = {abs(margin.mean()) / margin.std():.1f})"
    )
    for key in ("features", "gru"):
        x = np.concatenate(probe.rows[key])  # (D, units)
        sd = x.std(0)  # (units,)
        print(
            f"  {key}: {x.shape[1]} units, {int((sd < STILL).sum())} still (sd < {STILL}), "
            f"median sd {np.median(sd):.3f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", help="checkpoint.pt files or run directories")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--map", default="train-50")
    parser.add_argument("--driver", default="heuristic", help="any --policy of diacc eval")
    args = parser.parse_args()
    torch.set_num_threads(1)
    probes = [Probe(name) for name in args.checkpoints]
    policy = ProbingDriver(build_policy(parse_policy(args.driver)), probes)
    cell = Cell(map=args.map, n_vehicles=25, cav_penetration=0.4, style_mix="D1")
    settings = EvalSettings(style_preset="realistic", episode_steps=330)
    driver = EpisodeDriver(policy, probes[0].policy.env_config(cell, settings))
    for episode in range(args.episodes):
        driver.reset(cell.seed(episode, "validation"))
        while not driver.done:
            driver.step()
    driver.close()
    print(f"driven by {args.driver} on {args.map}, {args.episodes} validation episodes")
    for probe in probes:
        report(probe)


if __name__ == "__main__":
    try:
        main()
    except DiaccError as error:
        raise SystemExit(f"logit_probe.py: error: {error}") from None

"""Learning, honestly measured: a short DIACC run beats its own untrained policy.

Both policies are evaluated the same way, sampling from the actor, on seeds
the training never saw. The scenario is small (12 vehicles, 3 CAVs, 50-step
episodes) so that the CI-sized run fits in a few minutes on 2 cores; the slow
test trains twice as long and asks for a clearer margin.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from diacc.config import TrainConfig, override
from diacc.envs.episode import EpisodeDriver
from diacc.learn.checkpoint import load_checkpoint, restore
from diacc.learn.mappo import make_agent, train
from diacc.learn.models.inputs import to_tensors
from diacc.sim.scenario import Scenario

HELD_OUT_SEEDS = range(10_000, 10_030)


def small_config(run_dir, steps: int) -> TrainConfig:
    cfg = override(
        TrainConfig(),
        {
            "total_steps": steps,
            "n_envs": 4,
            "rollout_steps": 50,
            "env.sim.episode_steps": 50,
            "run_dir": str(run_dir),
            "device": "cpu",
            "seed": 3,
        },
    )
    return override(cfg, {"env.scenario": Scenario(n_vehicles=12, cav_penetration=0.25)})


class SampledActor:
    """The actor's actions sampled (not argmax), from one generator across episodes."""

    def __init__(self, actor: torch.nn.Module) -> None:
        self.actor, self.generator = actor, torch.Generator().manual_seed(0)

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        self.hidden = torch.zeros(n_cavs, self.actor.hidden_size)

    def act(self, actor_obs, first_step: bool) -> np.ndarray:
        # first_step: one flag for all CAV slots, or one per slot (refilled slots)
        flags = np.broadcast_to(np.asarray(first_step, bool), (self.hidden.shape[0],))
        start = torch.as_tensor(flags.copy())
        with torch.no_grad():
            logits, self.hidden = self.actor(to_tensors(actor_obs), self.hidden, start)
        probs = torch.softmax(logits, -1)
        return torch.multinomial(probs, 1, generator=self.generator).squeeze(-1).numpy()


def evaluate(cfg: TrainConfig, agent, seeds) -> tuple[float, float]:
    """(collision rate over episodes, mean CAV speed over episodes) with sampled actions."""
    driver = EpisodeDriver(SampledActor(agent.actor), cfg.env)
    collided, speeds = [], []
    try:
        for seed in seeds:
            driver.reset(seed)
            cav_speeds = []
            while not driver.done:
                state = driver.step()
                on_road = state.active & state.is_cav
                if on_road.any():
                    cav_speeds.append(state.speed_mps[on_road].mean())
            collided.append(float(len(state.collisions) > 0))
            speeds.append(float(np.mean(cav_speeds)))
    finally:
        driver.close()
    return float(np.mean(collided)), float(np.mean(speeds))


def untrained_and_trained(tmp_path, steps: int):
    cfg = small_config(tmp_path / "run", steps)
    train(cfg, progress=False)
    torch.manual_seed(cfg.seed)
    untrained = make_agent(cfg, torch.device("cpu"))  # the run's initial weights
    trained = make_agent(cfg, torch.device("cpu"))
    path = tmp_path / "run" / "checkpoint.pt"
    restore(trained, load_checkpoint(path), cfg, path)
    return evaluate(cfg, untrained, HELD_OUT_SEEDS), evaluate(cfg, trained, HELD_OUT_SEEDS)


def test_short_training_run_improves_speed_and_safety(tmp_path):
    (coll0, speed0), (coll1, speed1) = untrained_and_trained(tmp_path, steps=6_000)
    print(
        f"untrained: collisions {coll0:.2f}, CAV speed {speed0:.2f} m/s; "
        f"trained: collisions {coll1:.2f}, CAV speed {speed1:.2f} m/s"
    )
    assert speed1 > speed0 + 2.0
    assert coll1 <= coll0 and coll1 <= 0.1


def test_paper_training_scenario_episodes_rarely_collide(tmp_path):
    """The learning check of the paper's training scenario (train-50, N = 25, 10 CAVs),
    CI-sized: with PSAR, training episodes do not end in collisions from the start.
    Before PSAR could stop a CAV, every episode of the first 40k steps did."""
    cfg = override(
        TrainConfig(),
        {
            "env.map": "train-50",
            "total_steps": 2_000,
            "n_envs": 4,
            "run_dir": str(tmp_path / "run"),
            "device": "cpu",
            "seed": 1,
        },
    )
    train(cfg, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "progress.jsonl").open()]
    rates = [row["episode/collision"] for row in rows if "episode/collision" in row]
    assert len(rates) == 5
    assert float(np.mean(rates)) < 0.1, rates


@pytest.mark.slow
def test_longer_training_run_improves_clearly(tmp_path):
    (coll0, speed0), (coll1, speed1) = untrained_and_trained(tmp_path, steps=16_000)
    assert speed1 > speed0 + 5.0
    assert coll1 <= 0.5 * coll0

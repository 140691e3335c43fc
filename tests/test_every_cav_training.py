"""Every CAV an agent in demand training (issue 58 item 3): with ``cav_slots = "every"``
(the default) the slots cover every CAV of the episode, so the shared actor drives every
CAV on the road and none drives itself; the PPO update replays the CAVs, not the empty
slots. Tiny highway runs on a 160 m road (seconds)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP

from diacc.config import TrainConfig, override
from diacc.envs.actions import REMAIN
from diacc.envs.vector import make_vector_env
from diacc.learn.agent import make_agent
from diacc.learn.buffer import make_batch
from diacc.learn.mappo import seed_everything, train
from diacc.learn.ppo import collect_rollout, evaluate_batch, rollout_gae
from diacc.sim.scenario import Scenario

#: 20 vehicles enter over 20 s, half of them CAVs; more than 3 CAVs are on the road at once.
DEMAND = Scenario(kind="demand", inflow_vph=3600, demand_s=20, cav_penetration=0.5)


@pytest.fixture
def tiny(tmp_path) -> TrainConfig:
    """Two envs of :data:`DEMAND`, 40-step episodes, tiny networks."""
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    cfg = override(
        TrainConfig(),
        {"n_envs": 2, "rollout_steps": 40, "chunk_len": 10, "total_steps": 80, "epochs": 1,
         "device": "cpu", "env.map": str(road), "env.sim.episode_steps": 40,
         "model.hidden_dim": 32, "model.gru_hidden": 32, "model.cross_dim": 32,
         "run_dir": str(tmp_path / "run")},
    )  # fmt: skip
    return override(cfg, {"env.scenario": DEMAND})


def _slot_counts(cfg: TrainConfig) -> tuple[int, np.ndarray, np.ndarray]:
    """(agent slots, CAVs on the road (S, E), CAVs on the road without a slot (S, E)) of
    one 40-step rollout of ``cfg``'s envs, every CAV holding its speed."""
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, "batched")
    try:
        envs.reset(first_episode=0)
        on_road, unserved = [], []
        for _ in range(cfg.rollout_steps):
            out = envs.step(np.full((cfg.n_envs, envs.n_cavs), REMAIN))
            ((batch, _),) = envs.groups  # one map: one batch
            state = batch.state
            on_road.append((state.traffic.active & state.traffic.is_cav).sum(-1))
            unserved.append(state.unserved_cavs.copy())
            held = out.actor_obs.alive.sum(-1)  # (E,) slots whose CAV is on the road
            assert (held + unserved[-1] == on_road[-1])[~(out.terminated | out.truncated)].all()
        return envs.n_cavs, np.array(on_road), np.array(unserved)
    finally:
        envs.close()


def test_every_cav_on_the_road_holds_a_slot(tiny):
    slots, on_road, unserved = _slot_counts(tiny)
    assert slots == DEMAND.n_cavs == 10
    assert on_road.max() > 3 and not unserved.any()
    capped = override(tiny, {"env.scenario.cav_slots": 3})
    slots, on_road, unserved = _slot_counts(capped)
    assert slots == 3 and unserved.any()  # the cap leaves CAVs to drive themselves


def test_the_update_replays_what_every_cavs_did(tiny):
    """Slots filled as CAVs enter replay the rollout's own log-probs, from their hidden
    states, each with its env's critic sequence."""
    seed_everything(tiny.seed)
    agent = make_agent(tiny, torch.device("cpu"))
    envs = make_vector_env(tiny.env, tiny.n_envs, tiny.seed)
    try:
        roll, next_value, _ = collect_rollout(agent, envs, tiny, 0, global_step=0)
    finally:
        envs.close()
    adv, ret = rollout_gae(roll, next_value, tiny)
    batch = make_batch(roll, adv, ret, tiny.chunk_len, torch.device("cpu"))
    C = roll.alive.shape[2]
    assert C == DEMAND.n_cavs and not roll.alive.all()  # slots of CAVs not yet entered or gone
    with torch.no_grad():
        every_env = torch.arange(batch.critic_h0.shape[0])
        logprob, _, _, agents = evaluate_batch(agent, batch, every_env, C)
    alive = batch.alive[:, agents].bool()
    assert alive.any()
    ratio = (logprob - batch.logprobs[:, agents]).exp()[alive]
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=1e-5)


def test_demand_training_with_every_cav_an_agent(tiny):
    run = train(tiny, progress=False)
    config = json.loads((run / "config.json").read_text())
    assert config["env"]["scenario"]["cav_slots"] == "every"
    rows = [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and np.isfinite(rows[0]["value_loss"])
    assert "capped" not in (run / "train.log").read_text()


def test_a_capped_training_run_says_so(tiny):
    run = train(override(tiny, {"env.scenario.cav_slots": 3}), progress=False)
    assert "agent slots capped at 3 of the episode's 10 CAVs" in (run / "train.log").read_text()


def test_train_option_sets_the_slots():
    from diacc.config import build_train_config

    demand = {"env.scenario.kind": "demand"}
    assert build_train_config(sets=demand).env.scenario.cav_slots == "every"
    assert build_train_config(agent_slots=8, sets=demand).env.scenario.n_slots == 8
    scenario = build_train_config(agent_slots="every", sets=demand).env.scenario
    assert scenario.n_slots == scenario.n_cavs == 80

"""The shipped trained checkpoints (checkpoints/*.pt) load and drive both backends.

They are the agents of docs/results/trained-agent.md (and the no-PSAR agent of
docs/results/nopsar-learning.md): a refactor that cannot read them, or
a backend change that makes them crash, must fail here rather than in a
newcomer's first command.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from diacc.config import PSARConfig
from diacc.envs.episode import EpisodeDriver
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy
from diacc.learn.checkpoint import config_from_checkpoint

CHECKPOINTS = sorted((Path(__file__).resolve().parent.parent / "checkpoints").glob("*.pt"))
#: The agents that drive under PSAR; a ``-nopsar-`` agent brakes on its own (PSAR off).
PSAR_CHECKPOINTS = [path for path in CHECKPOINTS if "-nopsar-" not in path.name]


def test_checkpoints_are_shipped():
    assert CHECKPOINTS, "checkpoints/ holds no .pt file"


@pytest.mark.parametrize("backend", ["highway", "sumo"])
@pytest.mark.parametrize("path", CHECKPOINTS, ids=lambda p: p.name)
def test_checkpoint_drives_the_training_cell(path, backend):
    """Sampled actions under PSAR; a no-PSAR agent greedy, as it is evaluated (nothing
    would stop a sampled *lane left* into a neighbour)."""
    use_psar = path in PSAR_CHECKPOINTS
    variant = "diacc" if use_psar else "diacc-nopsar"
    policy = build_policy(PolicySpec(str(path), variant, sampled=use_psar))
    assert policy.base.sim.style_preset in path.name and policy.base.use_psar == use_psar
    cfg = policy.env_config(
        Cell("train-50", 25, 0.4, "D1"), EvalSettings(backend, episode_steps=20)
    )
    driver = EpisodeDriver(policy, cfg)
    try:
        state = driver.reset(seed=0)
        start_m = state.x_m[state.is_cav].copy()
        while not driver.done:
            state = driver.step()
    finally:
        driver.close()
    assert len(state.collisions) == 0 and driver.steps == 20
    assert (state.x_m[state.is_cav] > start_m + 100.0).all()  # every CAV drove on


@pytest.mark.parametrize("path", PSAR_CHECKPOINTS, ids=lambda p: p.name)
def test_checkpoint_keeps_the_psar_horizon_it_was_trained_with(path):
    """The default horizon changed to "headway" (2026-12-02); the paper-congestion agents
    were trained with "stopping" (the file name says the horizon of the others), which
    their stored config names and evaluation must keep."""
    import torch

    stored = torch.load(path, map_location="cpu", weights_only=True)["config"]
    trained = "headway" if "-headway-" in path.name else "stopping"
    assert stored["env"]["psar"]["horizon"] == trained
    assert PSARConfig().horizon == "headway"
    policy = build_policy(PolicySpec(str(path), "diacc"))
    cell = Cell("train-50", 25, 0.4, "D1")
    assert policy.env_config(cell, EvalSettings()).psar.horizon == trained
    # Only an explicit --psar-horizon changes it.
    literal = EvalSettings(psar_horizon="paper")
    assert policy.env_config(cell, literal).psar.horizon == "paper"
    # A stored config that predates the field loads with the default of its time.
    del stored["env"]["psar"]["horizon"]
    assert config_from_checkpoint({"config": stored}).env.psar.horizon == "stopping"
    stored["env"]["psar"]["horizon"] = "paper"
    assert config_from_checkpoint({"config": stored}).env.psar.horizon == "paper"


@pytest.mark.parametrize("path", PSAR_CHECKPOINTS, ids=lambda p: p.name)
def test_checkpoint_keeps_the_full_brake_rule_of_its_time(path):
    """PSAR's full_brake became "threat" (2026-12-03), then "known" (later that day); the
    agents trained before kept "bound", which their stored config lacks and loading must
    keep (the file name says "threat" or "known" of those trained with it, stored)."""
    import torch

    stored = torch.load(path, map_location="cpu", weights_only=True)["config"]
    assert PSARConfig().full_brake == "known"
    policy = build_policy(PolicySpec(str(path), "diacc"))
    cell = Cell("train-50", 25, 0.4, "D1")
    kept = stored["env"]["psar"].get("full_brake", "bound")
    named = [rule for rule in ("threat", "known") if f"-{rule}-" in path.name]
    assert kept == (named[0] if named else "bound")
    assert policy.env_config(cell, EvalSettings()).psar.full_brake == kept
    asked = EvalSettings(psar_full_brake="known")
    assert policy.env_config(cell, asked).psar.full_brake == "known"


@pytest.mark.parametrize("path", CHECKPOINTS, ids=lambda p: p.name)
def test_checkpoint_keeps_the_learner_it_was_trained_with(path):
    """The default learner became the shipped agents' (hidden 64, 4 minibatches,
    2026-12-02); a checkpoint's stored config decides its sizes, and one that lacked
    them would load with the paper's sizes, the defaults of its time."""
    import torch

    from diacc.config import PAPER_LEARNER, TrainConfig

    stored = torch.load(path, map_location="cpu", weights_only=True)["config"]
    cfg = config_from_checkpoint({"config": stored})
    assert (cfg.model.hidden_dim, cfg.model.gru_hidden, cfg.minibatches) == (64, 64, 4)
    assert cfg.model == TrainConfig().model
    for key in ("hidden_dim", "gru_hidden"):
        del stored["model"][key]
    del stored["minibatches"]
    old = config_from_checkpoint({"config": stored})
    assert (old.model.hidden_dim, old.model.gru_hidden, old.minibatches) == tuple(
        PAPER_LEARNER[k] for k in ("model.hidden_dim", "model.gru_hidden", "minibatches")
    )

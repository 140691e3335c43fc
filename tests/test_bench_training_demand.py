"""``python -m diacc.experiments.bench.training --only demand``: the demand scenario's row."""

from __future__ import annotations

from diacc.config import TrainConfig, override, validate
from diacc.experiments.bench import training


def test_the_demand_row_is_a_valid_demand_run_and_only_on_request():
    label, options, busy = training.DEMAND_ROW
    assert training.configurations("cpu", False, only="demand") == [training.DEMAND_ROW]
    assert label not in [row[0] for row in training.configurations("cpu", False)]
    cfg = override(
        TrainConfig(),
        {
            "n_envs": training.DEMAND_ENVS,
            "rollout_steps": training.DEMAND_ROLLOUT_STEPS,
            "run_dir": "unused",
            **options,
        },
    )
    validate(cfg)
    assert cfg.env.scenario.kind == "demand" and cfg.env.scenario.n_vehicles == 480
    # whole episodes per rollout, as a demand run trains
    assert cfg.rollout_steps == cfg.env.sim.episode_steps == 600 and not busy

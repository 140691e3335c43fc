"""Fine-tuning on a road with more vehicles on it: ``init_from`` across critic row counts.

The critic's row count (``env.obs.max_vehicles``) sizes the observation, not the
graph networks' weights, so a release-trained ``diacc`` agent starts a demand run
(hundreds of vehicles on the road); the MLP critic's weights depend on it, so
there it stays a one-line error.
"""

from __future__ import annotations

import pytest
import torch
from test_mappo import tiny_config

from diacc.learn.checkpoint import CheckpointError, init_networks, load_checkpoint
from diacc.learn.mappo import make_agent, train


@pytest.mark.parametrize("variant", ["diacc", "mappo-iadm"])
def test_init_from_takes_another_critic_row_count_where_the_weights_allow(tmp_path, variant):
    source = tiny_config(tmp_path / "a", total_steps=40, variant=variant)
    train(source, progress=False)
    path = tmp_path / "a" / "run" / "checkpoint.pt"
    more = {"env.obs.max_vehicles": 2 * source.env.obs.max_vehicles}
    tuned = tiny_config(
        tmp_path / "b", total_steps=40, init_from=str(path), variant=variant, **more
    )
    agent = make_agent(tuned, torch.device("cpu"))
    if variant == "mappo-iadm":  # MLP critic: its input width grows with the rows
        with pytest.raises(CheckpointError, match=r"does not match the mappo-iadm networks"):
            init_networks(agent, path, tuned)
        return
    init_networks(agent, path, tuned)
    saved = load_checkpoint(path)
    for name, tensor in agent.critic.state_dict().items():
        assert torch.equal(tensor, saved["critic"][name]), name
    train(tuned, progress=False)  # and the run trains with the larger rows
    assert load_checkpoint(tmp_path / "b" / "run" / "checkpoint.pt")["global_step"] == 40

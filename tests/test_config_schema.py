"""A checkpoint's config carries a schema version (issue 43): a stored config is
migrated step by step from its version, not by the dates its defaults changed."""

from __future__ import annotations

from dataclasses import asdict

import pytest
import torch
from test_mappo import tiny_config

from diacc.config import CONFIG_SCHEMA, ConfigError, TrainConfig, override, stored_config
from diacc.learn.checkpoint import CheckpointError, config_from_checkpoint, load_checkpoint


def _without(tree: dict, *keys: str) -> dict:
    """A copy of a stored config with the dotted ``keys`` removed."""
    tree = {k: dict(v) if isinstance(v, dict) else v for k, v in tree.items()}
    for key in keys:
        *parents, leaf = key.split(".")
        node = tree
        for name in parents:
            node[name] = dict(node[name])
            node = node[name]
        del node[leaf]
    return tree


def test_each_version_fills_a_missing_field_with_its_own_default():
    stored = asdict(TrainConfig())
    stored["env"] = {k: dict(v) if isinstance(v, dict) else v for k, v in stored["env"].items()}
    lost = _without(stored, "env.psar.horizon", "model.hidden_dim", "entropy_coef")
    old = stored_config(lost, 1)  # version 1: the defaults before they changed
    assert (old.env.psar.horizon, old.model.hidden_dim, old.entropy_coef) == ("stopping", 128, 0.01)
    new = stored_config(lost, CONFIG_SCHEMA)  # today's version: today's defaults
    assert new == TrainConfig()
    # a complete config means the same in every version
    assert stored_config(stored, 1) == stored_config(stored, CONFIG_SCHEMA) == TrainConfig()


def test_a_config_without_a_version_is_version_1():
    stored = _without(asdict(TrainConfig()), "env.psar.full_brake")
    assert config_from_checkpoint({"config": stored}).env.psar.full_brake == "bound"
    payload = {"config": stored, "config_schema": CONFIG_SCHEMA}
    assert config_from_checkpoint(payload).env.psar.full_brake == "known"


def test_version_2_agent_slots_mean_what_they_did():
    """Before version 3 ``cav_slots`` was 16 by default, a cap, and every release stored it;
    now it is ``"every"``: a stored demand keeps its cap, a release loads."""
    release = asdict(TrainConfig())
    release["env"] = {**release["env"], "scenario": {**release["env"]["scenario"], "cav_slots": 16}}
    assert stored_config(release, 2) == TrainConfig()
    with pytest.raises(ConfigError, match="cav_slots 16 is a demand setting"):
        stored_config(release, CONFIG_SCHEMA)  # today a release has no such setting
    demand = asdict(override(TrainConfig(), {"env.scenario.kind": "demand"}))
    del demand["env"]["scenario"]["cav_slots"]
    assert stored_config(demand, 2).env.scenario.n_slots == 16
    assert stored_config(demand, CONFIG_SCHEMA).env.scenario.cav_slots == "every"


@pytest.mark.parametrize(
    ("schema", "match"),
    [
        (CONFIG_SCHEMA + 1, f"config schema {CONFIG_SCHEMA + 1} is newer than this diacc's"),
        (0, "must be a positive integer, got 0"),
        ("2", "must be a positive integer, got '2'"),
        (True, "must be a positive integer, got True"),
    ],
)
def test_an_unknown_version_is_one_line(schema, match):
    with pytest.raises(ConfigError, match=match):
        stored_config(asdict(TrainConfig()), schema)


def test_training_stores_the_version_and_a_bad_one_is_refused(tmp_path):
    from diacc.learn.mappo import train

    run = train(tiny_config(tmp_path), progress=False, stop_after_updates=1)
    payload = load_checkpoint(run / "checkpoint.pt")
    assert payload["config_schema"] == CONFIG_SCHEMA
    payload["config_schema"] = CONFIG_SCHEMA + 5
    torch.save(payload, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="unusable config .*config schema .* is newer"):
        load_checkpoint(tmp_path / "future.pt")

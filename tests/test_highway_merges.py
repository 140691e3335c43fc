"""``SimConfig.highway_merges``: how the highway backend's human drivers leave an ending lane.

``late`` is every committed highway result's model; ``early`` starts forced merges
400 m before a lane end and lets followers yield sooner, which brings pure-HDV outflow
in oversaturation within 10 % of SUMO's (benchmarks/studies/demand-human-traffic).
Real simulators throughout.
"""

from __future__ import annotations

import pytest

from diacc.cli import main
from diacc.config import HIGHWAY_MERGES, ConfigError, SimConfig
from diacc.experiments.bench.fidelity import FlowSettings, human_flow
from diacc.experiments.policies import EvalSettings
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.backends.highway.models import MERGE_MODELS, HighwayModel
from diacc.sim.maps import load_map

#: A short oversaturated demand run: 4000 veh/h into train-50 for 180 s.
SHORT = {"demand_s": 180.0, "warmup_s": 60.0}


def test_every_name_has_a_model_and_late_is_the_default():
    assert set(HIGHWAY_MERGES) == set(MERGE_MODELS)
    assert SimConfig().highway_merges == "late"
    assert HighwayModel.of("late") == HighwayModel()
    early = HighwayBackend(load_map("train-50"), SimConfig(highway_merges="early")).model
    assert (early.merge_zone_m, early.yield_zone_m) == (400.0, 200.0)


def test_early_merges_pass_more_vehicles_with_shorter_waits_at_the_lane_end():
    late, early = (
        human_flow("pure-hdv", "highway", 4000.0, 0, FlowSettings(**SHORT, highway_merges=m))
        for m in ("late", "early")
    )
    assert early["outflow_vph"] > late["outflow_vph"]
    assert early["max_lane_end_wait_s"] < late["max_lane_end_wait_s"]
    assert early["n_collisions"] == late["n_collisions"] == 0


def test_sumo_ignores_the_setting():
    """SUMO's strategic lane changes are LC2013's own: the same traffic either way."""
    late, early = (
        human_flow(
            "pure-hdv",
            "sumo",
            3000.0,
            0,
            FlowSettings(demand_s=60.0, warmup_s=10.0, highway_merges=m),
        )
        for m in ("late", "early")
    )
    assert late["bin_vph"] == early["bin_vph"]
    assert late["delay_per_vehicle_s"] == early["delay_per_vehicle_s"]


def test_an_evaluation_applies_and_records_it_only_when_given():
    given = EvalSettings(highway_merges="early")
    assert given.apply(SimConfig()).highway_merges == "early"
    assert given.describe()["settings"]["highway_merges"] == "early"
    # Absent otherwise, so results written before the setting existed stay reusable.
    assert "highway_merges" not in EvalSettings().describe()["settings"]
    assert EvalSettings().apply(SimConfig(highway_merges="early")).highway_merges == "early"


def test_an_unknown_name_is_a_one_line_error(capsys):
    with pytest.raises(ConfigError, match="highway_merges"):
        SimConfig(highway_merges="eager")
    assert main(["bench", "--highway-merges", "early"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "diacc: error: --highway-merges needs --fidelity"


def test_simulate_takes_and_names_the_merge_model(capsys):
    argv = ["simulate", "--map", "train-50", "--episode-steps", "20", "--highway-merges"]
    assert main([*argv, "early"]) == 0
    assert "style preset realistic, early merges" in capsys.readouterr().out

"""Map and scenario validation: one test per rule, plus the shipped maps."""

from __future__ import annotations

import numpy as np
import pytest

from diacc.config import ConfigError, TrainConfig, override
from diacc.sim.maps import MapError, available_maps, load_map, parse_map
from diacc.sim.scenario import Scenario, ScenarioError, draw_population

GOOD = {
    "name": "t",
    "lane_width_m": 3.2,
    "drop_side": "left",
    "segments": [
        {"kind": "multilane", "length_m": 500, "lanes": 4, "speed_limit_mps": 25.0},
        {"kind": "reduction50", "length_m": 300, "lanes": 2, "speed_limit_mps": 25.0},
        {"kind": "multilane", "length_m": 500, "lanes": 4, "speed_limit_mps": 25.0},
    ],
}


def _with(seg_index: int | None = None, **changes) -> dict:
    data = {**GOOD, "segments": [dict(s) for s in GOOD["segments"]]}
    if seg_index is None:
        data.update(changes)
    else:
        data["segments"][seg_index].update(changes)
    return data


@pytest.mark.parametrize("name", ["train-25", "train-50", "test-25", "test-50"])
def test_shipped_maps_match_the_paper_route(name):
    road = load_map(name)
    assert road.length_m == pytest.approx(1300.0)
    assert road.max_lanes == 4 and road.max_speed_mps == 25.0
    reduced = [s for s in road.segments if s.kind != "multilane"]
    assert len(reduced) == 1
    assert reduced[0].lanes == (3 if name.endswith("25") else 2)
    assert reduced[0].kind == ("reduction25" if name.endswith("25") else "reduction50")


def test_test_maps_move_the_reduction():
    start = {n: load_map(n).segment_starts_m[1] for n in available_maps()}
    assert start["train-25"] != start["test-25"] and start["train-50"] != start["test-50"]


def test_lane_geometry_left_and_right_drops():
    left = parse_map(GOOD)
    right = parse_map(_with(drop_side="right"))
    assert list(left.lane_range(1)) == [0, 1] and list(right.lane_range(1)) == [2, 3]
    assert left.lane_end_m()[0].tolist() == [np.inf, np.inf, 500.0, 500.0]
    assert right.lane_end_m()[0].tolist() == [500.0, 500.0, np.inf, np.inf]
    assert left.segment_of(np.array([0.0, 499.9, 500.0, 1299.0, 2000.0])).tolist() == [
        0,
        0,
        1,
        2,
        2,
    ]


@pytest.mark.parametrize(
    ("data", "field"),
    [
        (_with(0, lanes=0), "segments[0].lanes"),
        (_with(1, length_m=-5), "segments[1].length_m"),
        (_with(0, speed_limit_mps=0), "segments[0].speed_limit_mps"),
        (_with(0, kind="tunnel"), "segments[0].kind"),
        (_with(2, colour="red"), "segments[2].colour"),
        (_with(lanes_total=4), "lanes_total"),
        (_with(1, lanes=1), "segments[1].lanes"),  # 4 -> 1 jumps by 3
        (_with(lane_width_m=0.5), "lane_width_m"),
        (_with(drop_side="up"), "drop_side"),
        (_with(segments=[]), "segments"),
    ],
)
def test_malformed_map_names_file_and_field(data, field):
    with pytest.raises(MapError) as err:
        parse_map(data, source="bad.toml")
    message = str(err.value)
    assert "\n" not in message and "bad.toml" in message and f"'{field}'" in message


def test_missing_field_and_unknown_map(tmp_path):
    data = _with()
    del data["segments"][0]["lanes"]
    with pytest.raises(MapError, match=r"segments\[0\]\.lanes' is missing"):
        parse_map(data)
    with pytest.raises(MapError, match="unknown map 'nowhere'"):
        load_map("nowhere")
    broken = tmp_path / "broken.toml"
    broken.write_text("name = [")
    with pytest.raises(MapError, match="broken.toml: not valid TOML"):
        load_map(broken)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"cav_penetration": 1.5}, "cav_penetration"),
        ({"cav_penetration": -0.1}, "cav_penetration"),
        ({"style_mix": (0.5, 0.5, 0.5)}, "style_mix"),
        ({"style_mix": "D9"}, "unknown style mix"),
        ({"n_vehicles": 0}, "n_vehicles"),
    ],
)
def test_invalid_scenarios(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        Scenario(**kwargs)


def test_more_cavs_than_vehicles():
    with pytest.raises(ScenarioError, match="12 CAVs requested but only 10 vehicles"):
        Scenario.with_cavs(10, 12)


def test_population_counts_styles_and_placement():
    road = load_map("train-25")
    pop = draw_population(Scenario(n_vehicles=25, cav_penetration=0.4, style_mix="D1"), road, 3)
    assert pop.is_cav.sum() == 10
    hdv_styles = np.bincount(pop.style[~pop.is_cav], minlength=3)
    assert hdv_styles.tolist() == [3, 9, 3]  # D1 0.2/0.6/0.2 of 15
    assert (pop.x_m <= 10 + 24 * 8).all() and set(pop.lane.tolist()) == {0, 1, 2, 3}
    # Round-robin lanes: vehicles of one lane start 4 slots (32 m) apart.
    for lane in range(4):
        assert np.all(np.diff(np.sort(pop.x_m[pop.lane == lane])) == 32.0)
    # No two vehicles share a slot.
    assert len(set(zip(pop.x_m.tolist(), pop.lane.tolist(), strict=True))) == 25


def test_population_is_seeded():
    road, sc = load_map("train-50"), Scenario(n_vehicles=30, style_mix="D3")
    a, b, c = (draw_population(sc, road, s) for s in (7, 7, 8))
    assert all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("is_cav", "style", "x_m"))
    assert not (np.array_equal(a.is_cav, c.is_cav) and np.array_equal(a.lane, c.lane))


def test_config_override_rejects_unknown_keys():
    cfg = override(TrainConfig(), {"lr": "0.001", "env.reward.w_ego": 0.8, "epochs": 3})
    assert cfg.lr == 0.001 and cfg.env.reward.w_ego == 0.8 and cfg.epochs == 3
    with pytest.raises(ConfigError, match="unknown config key 'env.reward.nope'"):
        override(cfg, {"env.reward.nope": 1})
    with pytest.raises(ConfigError, match="expects int"):
        override(cfg, {"epochs": "many"})

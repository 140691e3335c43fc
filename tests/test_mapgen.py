"""Generated bottleneck maps (diacc.sim.mapgen): seeded, disjoint streams, valid maps that
cover the documented distribution, built and stepped by both backends."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import sumolib
from helpers import first_env

from diacc.cli import main
from diacc.config import EnvConfig, resolve_road
from diacc.envs.env import BottleneckEnv
from diacc.envs.observation.layout import check_road
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.backends.sumo.backend import SumoBackend
from diacc.sim.backends.sumo.net import build_network
from diacc.sim.mapgen import (
    DISTRIBUTION,
    MAP_STREAMS,
    STREAM_SEEDS,
    generated_name,
    generated_names,
    generator_seed,
    map_data,
    map_toml,
    parse_generated_name,
    seed_stream,
)
from diacc.sim.maps import MapError, generate_map, load_map, map_tag, parse_map
from diacc.sim.scenario import Scenario, draw_population
from diacc.sim.settings import SimConfig
from diacc.sim.state import validate_state

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: 30 maps of each stream: the sample the distribution checks run on.
SAMPLE = [(stream, index) for stream in MAP_STREAMS for index in range(30)]


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    """SUMO networks go to a per-session cache, so the tests exercise netconvert."""
    monkeypatch.setenv("DIACC_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


def test_same_seed_same_map_and_a_pinned_one():
    for seed in (0, 1, 2_000_007):
        assert map_toml(seed) == map_toml(seed)
    assert len({map_toml(seed) for seed in range(20)}) == 20
    # The draws use SeedSequence words only, so this map is the same on every numpy version;
    # a change of distribution must give new names, not new maps under old names.
    assert generate_map("test", 7).description == (
        "Generated (seed 2000007), 1030 m, 22 m/s: 5 -> 3 lanes at 520-810 m (20 m/s)"
    )
    assert generate_map("test", 7).drop_side == "right"


def test_streams_own_disjoint_seed_ranges():
    ranges = [
        range(generator_seed(s, 0), generator_seed(s, STREAM_SEEDS - 1) + 1) for s in MAP_STREAMS
    ]
    assert [len(r) for r in ranges] == [STREAM_SEEDS] * len(MAP_STREAMS)
    for a, b in zip(ranges, ranges[1:], strict=False):
        assert a.stop == b.start  # consecutive, so no seed is in two streams
    rng = np.random.default_rng(0)
    for stream in MAP_STREAMS:
        for index in [0, STREAM_SEEDS - 1, *rng.integers(0, STREAM_SEEDS, 20).tolist()]:
            seed = generator_seed(stream, index)
            assert seed_stream(seed) == (stream, index)
            name = generated_name(stream, index)
            assert parse_generated_name(name) == (stream, index)
            assert map_data(seed)["name"] == name
    assert generate_map("train", 3) != generate_map("validation", 3) != generate_map("test", 3)


def test_a_sample_is_valid_and_covers_the_distribution():
    dist = DISTRIBUTION
    seen: dict[str, set] = {k: set() for k in ("lanes", "reductions", "dropped", "side", "kind")}
    route_speeds, reduction_speeds, lengths = [], [], []
    for stream, index in SAMPLE:
        road = load_map(generated_name(stream, index))
        # The TOML text is an ordinary map file: it loads to the same map.
        text = map_toml(generator_seed(stream, index))
        assert parse_map(tomllib.loads(text), source="text") == road
        assert map_tag(road.name) == road.name
        check_road(road)  # the observation layout holds it (lanes and segments)
        lanes = road.max_lanes
        reductions = [s for s in road.segments if s.kind != "multilane"]
        assert road.segments[0].kind == road.segments[-1].kind == "multilane"
        assert len(road.segments) == 2 * len(reductions) + 1
        for k, seg in enumerate(road.segments):
            assert (seg.kind == "multilane") == (k % 2 == 0)
            assert seg.length_m % dist.length_step_m == 0
        assert dist.approach_m[0] <= road.segments[0].length_m <= dist.approach_m[1]
        assert dist.exit_m[0] <= road.segments[-1].length_m <= dist.exit_m[1]
        for seg in road.segments[2:-1:2]:
            assert dist.between_m[0] <= seg.length_m <= dist.between_m[1]
        route_speed = road.segments[0].speed_limit_mps
        assert all(
            s.lanes == lanes and s.speed_limit_mps == route_speed for s in road.segments[::2]
        )
        for seg in reductions:
            dropped = lanes - seg.lanes
            assert 1 <= dropped <= 2 and seg.lanes >= 1
            assert dist.reduction_m[0] <= seg.length_m <= dist.reduction_m[1]
            assert dist.reduction_speed_min_mps <= seg.speed_limit_mps <= route_speed
            assert seg.kind == ("reduction25" if dropped / lanes < 0.375 else "reduction50")
            seen["dropped"].add(dropped)
            seen["kind"].add(seg.kind)
            reduction_speeds.append(seg.speed_limit_mps)
        # The largest release the critic pads for fits in the first segment.
        draw_population(Scenario(n_vehicles=40), road, seed=0)
        seen["lanes"].add(lanes)
        seen["reductions"].add(len(reductions))
        seen["side"].add(road.drop_side)
        route_speeds.append(route_speed)
        lengths.append(road.length_m)
    assert seen == {
        "lanes": {2, 3, 4, 5},
        "reductions": {1, 2},
        "dropped": {1, 2},
        "side": {"left", "right"},
        "kind": {"reduction25", "reduction50"},
    }
    assert (min(route_speeds), max(route_speeds)) == dist.route_speed_mps
    assert min(reduction_speeds) == dist.reduction_speed_min_mps
    shortest_m = dist.approach_m[0] + dist.reduction_m[0] + dist.exit_m[0]
    longest_m = dist.approach_m[1] + 2 * dist.reduction_m[1] + dist.between_m[1] + dist.exit_m[1]
    assert shortest_m <= min(lengths) < 1300 < max(lengths) <= longest_m  # around the shipped


def _drive_into_the_reduction(backend, road, scenario, steps=40):
    """Step idle commands: no collision, every vehicle on a lane that exists, and the
    leaders past the first segment (into the reduction)."""
    state = first_env(backend.reset(scenario, seed=1))
    for _ in range(steps):
        batch = backend.step(CavCommands.idle(scenario.n_vehicles))
        validate_state(batch)
        state = first_env(batch)
        assert state.collisions.shape == (0, 2)
        act = state.active
        assert road.lane_exists()[state.segment[act], state.lane[act]].all()
    assert state.x_m[state.active].max() > road.segments[0].length_m


@pytest.mark.parametrize(
    "name", ["gen-train-5", "gen-validation-1", "gen-test-8", "gen-test-9"]
)  # 2 lanes twice to 1 (left), 5 lanes right twice, 3 -> 1 twice right, 4 -> 2 left
def test_highway_builds_and_steps_generated_maps(name):
    road = load_map(name)
    backend = HighwayBackend(road, SimConfig())
    n = 25  # human drivers only: CAVs without commands would keep an ending lane
    _drive_into_the_reduction(backend, road, Scenario.with_cavs(n, 0))


@pytest.mark.parametrize("name", ["gen-validation-1", "gen-test-8"])
def test_sumo_builds_and_steps_generated_maps(name, tmp_path):
    road = load_map(name)
    net_path, _ = build_network(road, tmp_path)  # netconvert
    net = sumolib.net.readNet(str(net_path))
    for s, seg in enumerate(road.segments):
        edge = net.getEdge(f"e{s}")
        assert edge.getLaneNumber() == seg.lanes
        assert edge.getSpeed() == pytest.approx(seg.speed_limit_mps)
    n = 25
    sim = dataclasses.replace(SimConfig(), cav_mode="cooperative")
    with SumoBackend(road, sim) as backend:
        _drive_into_the_reduction(backend, road, Scenario(n_vehicles=n, cav_penetration=0.2))


def test_an_environment_takes_a_generated_map_name():
    assert generated_names("test", 3, start=5) == ["gen-test-5", "gen-test-6", "gen-test-7"]
    assert resolve_road(EnvConfig(map="gen-validation-3")) == generate_map("validation", 3)
    # Five segments, five lanes, dropping on the right: the agents' side of the env runs.
    config = EnvConfig(
        map="gen-validation-1", scenario=Scenario(n_vehicles=12, cav_penetration=0.25)
    )
    env = BottleneckEnv(config)
    try:
        env.reset_arrays(seed=3)
        for _ in range(20):
            out = env.step_arrays(np.zeros(env.n_cavs, np.int64))
            assert np.isfinite(out.reward)
            if out.terminated or out.truncated:
                break
    finally:
        env.close()


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: load_map("gen-nope-3"), "unknown map 'gen-nope-3'; generated maps are named"),
        (lambda: load_map("gen-test-07"), "unknown map 'gen-test-07'"),
        (lambda: load_map("gen-test-1000000"), "a stream's indices are 0-999999"),
        (lambda: load_map("nope"), "generated maps: gen-<train|validation|test>-<index>"),
        (lambda: generator_seed("dev", 1), "unknown map stream 'dev'; use train, validation"),
        (lambda: generator_seed("test", -1), r"map index must be an integer in \[0, 999999\]"),
        (lambda: generated_name("test", 1.5), "map index must be an integer"),
        (lambda: seed_stream(3 * STREAM_SEEDS), r"generator seed must be .* \[0, 2999999\]"),
        (lambda: seed_stream(True), "generator seed must be an integer"),
        (lambda: generated_names("test", 0), "a count of generated maps must be"),
        (lambda: generated_names("test", 2, start=999_999), "map index must be an integer"),
    ],
)
def test_bad_names_seeds_and_streams_are_one_line_errors(call, message):
    with pytest.raises(MapError, match=message) as info:
        call()
    assert "\n" not in str(info.value)


def _error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    return err


def test_cli_generate_prints_or_writes_the_map(tmp_path, capsys):
    assert main(["maps", "generate", "--stream", "test", "--index", "7"]) == 0
    assert capsys.readouterr().out == map_toml(2_000_007)
    assert main(["maps", "generate", "--seed", "2000007"]) == 0
    assert capsys.readouterr().out == map_toml(2_000_007)
    out = tmp_path / "g.toml"
    assert main(["maps", "generate", "--seed", "1000002", "--out", str(out)]) == 0
    assert load_map(out) == load_map("gen-validation-2")
    assert "generator seed must be" in _error(capsys, ["maps", "generate", "--seed", "-1"])
    assert "--index needs --stream" in _error(capsys, ["maps", "generate", "--index", "1"])
    both = ["maps", "generate", "--seed", "1", "--stream", "test"]
    assert "not both" in _error(capsys, both)
    missing = ["maps", "generate", "--seed", "1", "--out", str(tmp_path / "no" / "g.toml")]
    assert "cannot write" in _error(capsys, missing)

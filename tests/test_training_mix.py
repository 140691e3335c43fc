"""The training mix (``[mix]``, diacc.config.mix and diacc.envs.mix): config and its
refusals, seeded draws, padded agent slots, exact resume, and real runs on both backends."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP

from diacc.config import (
    ConfigError,
    TrainConfig,
    build_train_config,
    override,
    train_slots,
    validate,
)
from diacc.config.mix import MixConfig
from diacc.envs.mix import Cell, cells_of_envs, draw_cells, redraw_index
from diacc.envs.vector import make_vector_env
from diacc.learn.agent import make_agent
from diacc.learn.checkpoint import CheckpointError, load_checkpoint
from diacc.learn.mappo import seed_everything, train
from diacc.learn.ppo import collect_rollout
from diacc.learn.trainer import check_config
from diacc.sim.scenario import Scenario

#: A tiny learner and episode (tests/test_mappo.py's) over 4 envs.
TINY = {
    "n_envs": 4,
    "rollout_steps": 20,
    "chunk_len": 10,
    "total_steps": 320,
    "device": "cpu",
    "epochs": 1,
    "minibatches": 2,
    "env.sim.episode_steps": 15,
    "model.hidden_dim": 16,
    "model.gru_hidden": 16,
    "model.cross_dim": 16,
}


def tiny_mix(tmp_path, run: str = "run", **mix) -> dict:
    """Overrides of a run (in ``tmp_path / run``) on two short roads (lanes dropping left
    and right), with releases of 6-10 vehicles and demands of up to 10 at CAV shares
    0.3-0.7."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    left, right = tmp_path / "left.toml", tmp_path / "right.toml"
    left.write_text(SHORT_MAP)
    right.write_text(SHORT_MAP.replace('name = "short"', 'name = "right"\ndrop_side = "right"'))
    values = {
        "maps": (str(left), str(right)),
        "n_vehicles": (6, 10),
        "cav_penetration": (0.3, 0.7),
        "kind": ("release", "demand"),
        "inflow_vph": (1800.0, 3600.0),
        "demand_s": 10.0,
        "style_mix": ("D1", "D3"),
        "style_preset": ("realistic", "paper-congestion"),
        "blocks": 2,
        **mix,
    }
    return {
        **TINY,
        "run_dir": str(tmp_path / run),
        **{f"mix.{key}": value for key, value in values.items()},
    }


# ----------------------------------------------------------------------------- config
def test_mix_from_a_toml_file_and_set_is_one_checked_section(tmp_path):
    path = tmp_path / "mix.toml"
    path.write_text(
        "[mix]\n"
        'maps = ["train-50", "train-25"]\n'
        "generated_maps = 3\n"
        "n_vehicles = [15, 40]\n"
        "cav_penetration = [0.1, 0.8]\n"
        'kind = ["release", "demand"]\n'
        "inflow_vph = [2400, 4800]\n"
    )
    cfg = build_train_config(path, sets=["mix.redraw_every=2"])
    assert cfg.mix.on and cfg.mix.redraw_every == 2
    assert cfg.mix.map_names() == ("train-50", "train-25", *(f"gen-train-{i}" for i in range(3)))
    assert cfg.mix.inflow_vph == (2400.0, 4800.0) and cfg.mix.n_vehicles == (15, 40)
    validate(cfg)
    # 0.8 x 40 CAVs of a release, 0.8 x 4800 veh/h x 30 s = 32 of a demand
    assert train_slots(cfg) == 32
    assert not build_train_config().mix.on and train_slots(build_train_config()) == 10
    assert build_train_config(sets=["mix.n_vehicles=12,20"]).mix.n_vehicles == (12, 20)


@pytest.mark.parametrize(
    ("sets", "message"),
    [
        (["mix.maps=train-50,nowhere"], "mix.maps: "),
        (
            ["mix.maps=train-50", "mix.style_preset=paper", "env.sim.style_preset=zipper"],
            "mix.style_preset and env.sim.style_preset",
        ),
        (
            ["mix.maps=train-50", "mix.n_vehicles=15,30", "env.scenario.n_vehicles=30"],
            "mix.n_vehicles and env.scenario.n_vehicles",
        ),
        (["mix.maps=train-50", "mix.n_vehicles=30,20"], "low <= high"),
        (["mix.maps=train-50", "mix.cav_penetration=0.2"], "a range"),
        (["mix.maps=train-50", "mix.n_vehicles=20,45"], "exceeds env.obs.max_vehicles 40"),
        (["mix.maps=train-50", "mix.kind=demand", "mix.inflow_vph=2400,6000"], "a demand"),
        (["mix.maps=train-50", "mix.style_preset=realistic,fast"], "unknown 'fast'"),
        (["mix.maps=train-50", "mix.cav_penetration=0,0.5"], "makes 0 CAVs"),
        (["mix.maps=train-50", "mix.blocks=30"], "mix.blocks 30"),
        (["mix.maps=train-50", "extra_maps=train-25"], "extra_maps and mix.maps"),
        (["mix.maps=train-50", "mix.generated_maps=-1"], "mix.generated_maps"),
        (["mix.maps=train-50", "mix.backends=highway,carla"], "unknown 'carla'"),
        (
            ["mix.maps=train-50", "mix.backends=highway,sumo", "env.backend=sumo"],
            "mix.backends and env.backend",
        ),
    ],
)
def test_bad_mixes_are_one_line_config_errors_before_anything_runs(sets, message):
    with pytest.raises(ConfigError, match=message) as info:
        validate(build_train_config(sets=sets))
    assert "\n" not in str(info.value)


def test_a_changed_mix_is_refused_on_resume(tmp_path):
    cfg = override(TrainConfig(), tiny_mix(tmp_path))
    train(cfg, progress=False, stop_after_updates=1)
    stored = json.loads((tmp_path / "run" / "config.json").read_text())
    assert stored["mix"]["n_vehicles"] == [6, 10]
    changed = override(cfg, {"mix.n_vehicles": (6, 9)})
    with pytest.raises(CheckpointError, match="mix.n_vehicles"):
        train(changed, resume=True, progress=False)


# ----------------------------------------------------------------------------- draws
def test_draws_are_seeded_by_run_redraw_and_block():
    mix = MixConfig(
        maps=("train-50", "train-25"),
        generated_maps=5,
        n_vehicles=(15, 40),
        cav_penetration=(0.1, 0.8),
        kind=("release", "demand"),
        inflow_vph=(2400.0, 4800.0),
        style_mix=("D1", "D2", "D3"),
        blocks=4,
    ).following(Scenario(), "realistic", "highway")  # preset, backend: the run's own
    base = Scenario()
    first = draw_cells(mix, base, run_seed=3, redraw=7)
    assert first == draw_cells(mix, base, run_seed=3, redraw=7)
    assert first != draw_cells(mix, base, run_seed=3, redraw=8)
    assert first != draw_cells(mix, base, run_seed=4, redraw=7)
    many = [c for r in range(40) for c in draw_cells(mix, base, 1, r)]
    assert {c.scenario.kind for c in many} == {"release", "demand"}
    assert len({c.map for c in many}) == 7
    for cell in many:
        s = cell.scenario
        assert 0.1 <= s.cav_penetration <= 0.8 and s.style_mix in ("D1", "D2", "D3")
        if s.kind == "release":
            assert 15 <= s.n_vehicles <= 40
        else:
            assert 2400 <= s.inflow_vph <= 4800 and s.cav_slots == "every"
    assert [redraw_index(dataclasses.replace(mix, redraw_every=3), u) for u in range(7)] == [
        0, 0, 0, 1, 1, 1, 2,
    ]  # fmt: skip
    envs = cells_of_envs(first, 10)
    assert envs[:3] == [first[0]] * 3 and envs[-2:] == [first[3]] * 2


# ----------------------------------------------------------------------------- padding
def test_padded_slots_never_hold_a_cav_and_add_nothing(tmp_path):
    """Two cells with 2 and 6 CAVs: the first's envs get 4 dead slots (not alive, zero
    features, every action allowed), which the rollout stores as dead and the team
    reward weighs 0."""
    cfg = override(TrainConfig(), tiny_mix(tmp_path))
    small = Cell(
        str(tmp_path / "left.toml"),
        Scenario(n_vehicles=6, cav_penetration=0.34),
        "paper",
        "highway",
    )
    big = Cell(
        str(tmp_path / "right.toml"),
        Scenario(n_vehicles=10, cav_penetration=0.6),
        "paper",
        "highway",
    )
    assert (small.scenario.n_slots, big.scenario.n_slots) == (2, 6)
    for mode in ("batched", "sync"):
        envs = make_vector_env(
            cfg.env, 4, cfg.seed, mode, env_cells=[small, small, big, big], n_slots=6
        )
        try:
            seed_everything(cfg.seed)
            agent = make_agent(cfg, torch.device("cpu"))
            roll, _, _ = collect_rollout(agent, envs, cfg, 0, global_step=0)
        finally:
            envs.close()
        assert roll.alive.shape == (20, 4, 6)
        assert not roll.alive[:, :2, 2:].any() and roll.alive[0, :2, :2].all()
        assert roll.alive[0, 2:].all()
        obs = roll.actor_obs[5]
        assert not obs.self_state[:2, 2:].any() and obs.action_mask[:2, 2:].all()
        assert np.isfinite(roll.rewards).all() and np.isfinite(roll.logprobs).all()


# ----------------------------------------------------------------------------- runs
def test_a_resumed_mix_run_draws_the_same_cells_and_weights(tmp_path):
    """2 + 2 updates = 4 updates (redraws every update), and the log names each draw."""
    runs = {}
    for name, stop in (("a", None), ("b", 2)):
        cfg = override(TrainConfig(), tiny_mix(tmp_path, run=name))
        train(cfg, progress=False, stop_after_updates=stop)
        if stop:
            train(cfg, resume=True, progress=False)
        runs[name] = load_checkpoint(tmp_path / name / "checkpoint.pt")
    assert runs["a"]["update"] == runs["b"]["update"] == 4
    for part in ("actor", "critic"):
        for key, tensor in runs["a"][part].items():
            assert torch.allclose(tensor, runs["b"][part][key], atol=1e-6), f"{part}.{key}"
    logs = [(tmp_path / n / "train.log").read_text() for n in ("a", "b")]
    draws = [[line.split("mix draw")[1] for line in log.splitlines() if "mix draw" in line]
             for log in logs]  # fmt: skip
    assert len(draws[0]) == 4 and draws[0] == draws[1]
    rows = (tmp_path / "a" / "progress.jsonl").read_text().splitlines()
    assert len(rows) == 4


def test_highway_run_on_a_shipped_and_a_generated_map(tmp_path):
    sets = {
        **TINY,
        "env.sim.episode_steps": 50,
        "rollout_steps": 50,
        "total_steps": 400,
        "run_dir": str(tmp_path / "run"),
        "mix.maps": ("train-25", "gen-train-0"),
        "mix.n_vehicles": (10, 20),
        "mix.cav_penetration": (0.2, 0.6),
        "mix.blocks": 2,
    }
    cfg = override(TrainConfig(), sets)
    check_config(cfg)
    train(cfg, progress=False)
    log = (tmp_path / "run" / "train.log").read_text()
    assert log.count("mix draw") == 2
    assert "train-25" in log or "gen-train-0" in log
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["global_step"] == 400


def _sumo_mix(tmp_path) -> dict:
    return {
        **TINY,
        "n_envs": 2,
        "total_steps": 80,
        "env.backend": "sumo",
        "vector": "sync",
        "run_dir": str(tmp_path / "run"),
        "mix.maps": ("train-25", "test-25"),
        "mix.n_vehicles": (6, 10),
        "mix.blocks": 2,
    }


def test_sumo_envs_take_new_cells(tmp_path):
    """A block rebuilt on SUMO (its libsumo restarts) steps on its new road."""
    pytest.importorskip("libsumo")
    cfg = override(TrainConfig(), _sumo_mix(tmp_path))
    cells = draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, 0)
    envs = make_vector_env(
        cfg.env, 2, cfg.seed, "sync", env_cells=cells_of_envs(cells, 2), n_slots=train_slots(cfg)
    )
    try:
        envs.reset(0)
        envs.step(np.zeros((2, envs.n_cavs), np.int64))
        other = [
            Cell("test-25", Scenario(n_vehicles=6, cav_penetration=0.5), "realistic", "sumo")
        ] * 2
        envs.set_cells(other)
        actor, _ = envs.reset(1)
        assert actor.alive.sum(axis=1).tolist() == [3, 3]
        out = envs.step(np.zeros((2, envs.n_cavs), np.int64))
        assert not out.crashed.any()
    finally:
        envs.close()


def test_sumo_run_with_a_two_map_mix(tmp_path):
    pytest.importorskip("libsumo")
    cfg = override(TrainConfig(), _sumo_mix(tmp_path))
    train(cfg, progress=False)
    assert (tmp_path / "run" / "train.log").read_text().count("mix draw") == 2


def test_worker_processes_take_new_cells(tmp_path):
    """``vector = "process"``: each worker rebuilds its envs' batches on a new draw, and
    the joined steps are padded as the in-process ones."""
    cfg = override(TrainConfig(), tiny_mix(tmp_path))
    first = cells_of_envs(draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, 0), 4)
    envs = make_vector_env(cfg.env, 4, cfg.seed, "process", env_cells=first, n_slots=6)
    try:
        for redraw in (0, 1):
            cells = cells_of_envs(draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, redraw), 4)
            envs.set_cells(cells)
            actor, _ = envs.reset(redraw)
            assert actor.alive.shape == (4, 6)
            out = envs.step(np.zeros((4, 6), np.int64))
            assert out.actor_obs.alive.shape == (4, 6) and not out.crashed.any()
            for e, cell in enumerate(cells):
                if cell.scenario.kind == "release":  # every CAV on the road at the start
                    assert actor.alive[e].sum() == cell.scenario.n_slots
                assert not actor.alive[e, cell.scenario.n_slots :].any()
    finally:
        envs.close()


def test_overlap_collects_the_next_updates_cells(tmp_path):
    """With ``overlap`` the next rollout is collected during an update: on its own draw."""
    cfg = override(TrainConfig(), {**tiny_mix(tmp_path), "overlap": True, "mix.redraw_every": 2})
    train(cfg, progress=False)
    log = (tmp_path / "run" / "train.log").read_text()
    assert [line.split(": mix draw ")[1][0] for line in log.splitlines() if "mix draw" in line] == [
        "0",
        "1",
    ]
    assert "update 3: mix draw 1" in log


def test_dimensions_a_mix_leaves_out_are_the_runs_own():
    """Nothing the user set is dropped: a mix that lists only maps trains the run's own
    N, CAV share, style mix and driver preset on them."""
    cfg = build_train_config(
        sets=[
            "mix.maps=train-50,train-25",
            "env.scenario.n_vehicles=30",
            "env.scenario.cav_penetration=0.5",
            "env.sim.style_preset=paper-congestion",
        ]
    )
    assert cfg.mix.n_vehicles == (30, 30)
    assert cfg.mix.cav_penetration == (0.5, 0.5)
    assert cfg.mix.style_preset == ("paper-congestion",)
    assert cfg.mix.style_mix == ("D1",) and cfg.mix.kind == ("release",)
    assert cfg.mix.backends == ("highway",)


def test_blocks_take_the_backends_in_turn_without_moving_the_draws():
    """``mix.backends``: block b on backends[b % len]; the other dimensions' draws are
    those of a mix on one backend (no random number is spent on the backend)."""
    one = build_train_config(sets=["mix.maps=train-50,train-25", "mix.blocks=4"])
    two = override(one, {"mix.backends": ("highway", "sumo")})
    for redraw in range(3):
        cells = draw_cells(two.mix, two.env.scenario, 1, redraw)
        assert [c.backend for c in cells] == ["highway", "sumo"] * 2
        same = draw_cells(one.mix, one.env.scenario, 1, redraw)
        assert [dataclasses.replace(c, backend="highway") for c in cells] == same


def test_a_run_on_both_backends_at_once(tmp_path):
    """One run, one highway block (one batched simulator) and one SUMO block (one
    libsumo per env): both step, train, and resume; the one cell's draw, the same at
    every update, is logged once, not again on resume."""
    pytest.importorskip("libsumo")
    sets = {
        **TINY,
        "total_steps": 160,
        "run_dir": str(tmp_path / "run"),
        "env.scenario.n_vehicles": 8,
        "mix.maps": ("train-50",),
        "mix.backends": ("highway", "sumo"),
        "mix.blocks": 2,
    }
    cfg = override(TrainConfig(), sets)
    check_config(cfg)
    envs = make_vector_env(
        cfg.env,
        4,
        cfg.seed,
        "batched",
        env_cells=cells_of_envs(draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, 0), 4),
        n_slots=train_slots(cfg),
    )
    try:
        (highway, _), (sumo, _) = envs.groups
        assert highway.sims.batched and [b.name for b in highway.sims.backends] == ["highway"]
        assert not sumo.sims.batched and [b.name for b in sumo.sims.backends] == ["sumo"] * 2
        actor, _ = envs.reset(0)
        assert actor.alive.sum(axis=1).tolist() == [3, 3, 3, 3]
        out = envs.step(np.zeros((4, envs.n_cavs), np.int64))
        assert not out.crashed.any()
    finally:
        envs.close()
    train(override(cfg, {"total_steps": 80}), progress=False)
    train(cfg, resume=True, progress=False)
    log = (tmp_path / "run" / "train.log").read_text()
    assert "envs 0-1: train-50 release N8 cav0.40 D1 realistic highway" in log
    assert "envs 2-3: train-50 release N8 cav0.40 D1 realistic sumo" in log
    assert log.count("mix draw") == 1 and "checkpoint: update 2," in log
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["global_step"] == 160

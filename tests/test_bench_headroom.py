"""``diacc bench --headroom`` and ``--headway`` at a tiny size, and their bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import SHORT_MAP, make_state

from diacc.cli import main
from diacc.config import ConfigError
from diacc.experiments.bench import headroom, headway
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy


def test_time_gaps_by_pair_class():
    # Lane 1: HDV 0 at 10 m/s behind CAV 1 behind HDV 2; lane 2: a slow CAV (not moving).
    x, lane = [100.0, 125.0, 150.0, 100.0], [1, 1, 1, 2]
    state = make_state(x, lane, [10.0, 20.0, 20.0, 4.0], is_cav=[False, True, False, True])
    gaps = headway.time_gaps(state)
    assert gaps["hdv"].tolist() == pytest.approx([2.0])  # 20 m / 10 m/s
    assert gaps["cav_behind_hdv"].tolist() == pytest.approx([1.0])  # 20 m / 20 m/s
    assert gaps["cav_behind_cav"].size == 0
    # At its 20 m/s limit the CAV cruises: not counted as following.
    limits = np.full(8, 20.0)
    assert headway.time_gaps(state, limits)["cav_behind_hdv"].size == 0
    assert headway.time_gaps(state, limits)["hdv"].tolist() == pytest.approx([2.0])


def test_headroom_tiny(capsys):
    rows = headroom.run(maps=("train-25",), episodes=1, steps=15, horizon="headway")
    out = capsys.readouterr().out
    assert "free-flow travel 52.0 s" in out and "PSAR horizon headway" in out
    assert [r.label for r in rows] == [label for label, _, _ in headroom.REFERENCES]
    for row in rows:
        assert row.values["collision"] == 0.0 and row.values["delay_per_vehicle_s"] >= 0.0
    assert "| 100 % CAVs heuristic |" in out


def test_headroom_and_headway_bad_input(capsys):
    with pytest.raises(ConfigError, match="unknown style preset"):
        headroom.run(style_preset="rush-hour")
    err_lines = []
    for argv in (
        ["bench", "--headroom", "--episodes", "0"],
        ["bench", "--headway", "--episode-steps", "0"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("diacc: error: ") and "\n" not in err
        err_lines.append(err)
    assert (
        "--episodes must be in [1, 10000], got 0" in err_lines[0]
        and "--episode-steps must be in [1, 10000], got 0" in err_lines[1]
    )
    with pytest.raises(SystemExit):  # argparse: unknown horizon
        main(["bench", "--headroom", "--horizon", "tight"])


def test_headroom_demand_tiny(tmp_path, capsys):
    """Every reference row on a tiny demand run; the heuristic rows drive every CAV."""
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    # 30 vehicles enter over 30 s on a 160 m road; metrics from 10 s on.
    demand = headroom.demand_scenario(3600, demand_s=30, warmup_s=10)
    rows = headroom.run(maps=(str(road),), episodes=1, demand=demand, horizon="headway")
    out = capsys.readouterr().out
    assert "demand 3600 veh/h for 30 s (N = 30), warm-up 10 s" in out and "preset zipper" in out
    assert "| throughput vs pure HDV |" in out and "| unslotted CAV-steps |" in out
    assert [r.label for r in rows] == [label for label, _, _ in headroom.REFERENCES]
    by_label = {r.label: r.values for r in rows}
    for label in ("heuristic", "100 % CAVs heuristic"):
        assert by_label[label]["unslotted_cav_steps"] == 0.0
    for values in by_label.values():
        assert values["throughput_vph"] > 0 and values["collision"] == 0.0
    # The count can fail: with one slot, 100 % CAVs leave CAVs without one.
    policy = build_policy(PolicySpec("heuristic"))
    one_slot = dataclasses.replace(demand, cav_slots=1)
    sim = dataclasses.replace(policy.base.sim, episode_steps=30)
    policy.base = dataclasses.replace(policy.base, scenario=one_slot, sim=sim)
    cell = Cell(str(road), demand.n_vehicles, 1.0, "D1", demand.inflow_vph)
    driver = headroom.SlotCountingDriver(
        policy, policy.env_config(cell, EvalSettings("highway", 30, "zipper", agent_slots="own"))
    )
    try:
        run_episode(driver, cell, 0, "legacy")
    finally:
        driver.close()
    assert driver.unslotted_cav_steps > 0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--scenario", "demand", "--inflow", "-100"], "--inflow must be in (0, 10000]"),
        (["--scenario", "demand", "--inflow", "1e6"], "--inflow must be in (0, 10000]"),
        (["--scenario", "demand", "--inflow", "3600", "--warmup-s", "600"], "longer than warmup"),
        (
            ["--scenario", "demand", "--inflow", "3600", "--episode-steps", "100"],
            "is not shorter than",
        ),
        (["--scenario", "demand"], "--scenario demand needs --inflow"),
        (["--inflow", "3600"], "--inflow needs --headroom with --scenario demand"),
    ],
)
def test_headroom_demand_bad_input(capsys, argv, message):
    assert main(["bench", "--headroom", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert message in err
    # The demand flags belong to --headroom only.
    assert main(["bench", "--headway", "--scenario", "demand"]) == 2
    assert "--scenario demand needs --headroom with" in capsys.readouterr().err


SHIPPED = "checkpoints/diacc-train50-realistic-headway-threat-s1.pt"


def test_headroom_agent_rows_on_the_references_traffic(tmp_path, capsys):
    """A checkpoint's rows follow the references on the same seeds, a slot for every CAV,
    with their change against same-mix; greedy and sampled actions differ."""
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    demand = headroom.demand_scenario(3600, demand_s=30, warmup_s=10)
    references = tuple(r for r in headroom.REFERENCES if r[0] in ("pure HDV", "same-mix"))
    rows = headroom.run(
        maps=(str(road),), episodes=1, demand=demand, references=references,
        agents=(SHIPPED,), agent_actions=("greedy", "sampled"),
    )  # fmt: skip
    out = capsys.readouterr().out
    name = "diacc-train50-realistic-headway-threat-s1"
    assert [r.label for r in rows] == ["pure HDV", "same-mix", f"{name} greedy", f"{name} sampled"]
    assert "| delay vs same-mix | throughput vs same-mix |" in out
    agent = rows[2].values
    assert agent["unslotted_cav_steps"] == 0.0 and agent["collision"] == 0.0
    assert agent != rows[1].values  # the CAVs drive differently from the humans in their slots
    same_mix_delay = rows[1].values["delay_per_vehicle_s"]
    change = (agent["delay_per_vehicle_s"] - same_mix_delay) / same_mix_delay
    assert f"{name} greedy |" in out and f"| {change:+.0%} |" in out


def test_headroom_agent_bad_input(capsys):
    assert main(["bench", "--headway", "--agent", SHIPPED]) == 2
    assert "--agent needs --headroom" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="unknown agent actions 'best'"):
        headroom.run(agents=(SHIPPED,), agent_actions=("best",))
    assert headroom.pick_references("same-mix, cavs-100") == (
        headroom.REFERENCES[1],
        headroom.REFERENCES[4],
    )
    for bad in ("same-mix,humans", ","):
        with pytest.raises(ConfigError, match="unknown --references entry"):
            headroom.pick_references(bad)
    assert main(["bench", "--headway", "--references", "same-mix"]) == 2
    assert "--references needs --headroom" in capsys.readouterr().err
    # A missing agent is refused before the references run (they take minutes).
    assert main(["bench", "--headroom", "--agent", "runs/none/checkpoint.pt"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "diacc: error: checkpoint runs/none/checkpoint.pt does not exist"

"""``diacc bench --fidelity``: pure-HDV outflow of both backends side by side (real simulators)."""

from __future__ import annotations

import json

import pytest

from diacc.cli import main
from diacc.experiments.bench.fidelity import FlowSettings, capacity_drop, human_flow, run


def test_the_table_puts_both_backends_side_by_side(capsys):
    settings = FlowSettings(demand_s=40.0, warmup_s=10.0)
    records = run((3000.0,), seeds=1, settings=settings)
    out = capsys.readouterr().out
    assert [(r["backend"], r["inflow_vph"]) for r in records] == [
        ("highway", 3000.0),
        ("sumo", 3000.0),
    ]
    row = next(line for line in out.splitlines() if line.startswith("| 3000 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    outflow = {"highway": float(cells[1]), "sumo": float(cells[4])}
    assert outflow == {r["backend"]: pytest.approx(r["outflow_vph"], abs=0.5) for r in records}
    assert cells[7].startswith(f"{outflow['highway'] / outflow['sumo'] - 1:+.1%}")
    # The same record as benchmarks/studies/demand-human-traffic/run.py writes, seed for seed.
    again = human_flow("pure-hdv", "sumo", 3000.0, 0, settings)
    assert json.dumps({**again, "seconds": 0}) == json.dumps({**records[1], "seconds": 0})


def test_capacity_drop_needs_a_breakdown_and_a_lower_discharge():
    assert capacity_drop({"pre_breakdown_vph": 3960.0, "discharge_vph": 3753.0})
    assert not capacity_drop({"pre_breakdown_vph": 3480.0, "discharge_vph": 3810.0})
    assert not capacity_drop({"pre_breakdown_vph": None, "discharge_vph": None})


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--inflow", "-5"], "--inflow must be in (0, 10000]"),
        (["--demand-s", "60", "--warmup-s", "90"], "longer than warmup"),
    ],
)
def test_bad_fidelity_input_is_a_one_line_error(capsys, argv, message):
    assert main(["bench", "--fidelity", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert message in err

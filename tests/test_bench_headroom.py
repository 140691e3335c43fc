"""``diacc bench --headroom`` and ``--headway`` at a tiny size, and their bad input."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import make_state

from diacc.bench import headroom, headway
from diacc.cli import main
from diacc.config import ConfigError


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
        ["bench", "--headway", "--steps", "0"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("diacc: error: ") and "\n" not in err
        err_lines.append(err)
    assert "--episodes must be >= 1" in err_lines[0] and "--steps must be >= 1" in err_lines[1]
    with pytest.raises(SystemExit):  # argparse: unknown horizon
        main(["bench", "--headroom", "--horizon", "tight"])

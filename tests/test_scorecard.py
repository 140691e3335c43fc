"""`diacc scorecard` at a tiny budget: the training suite on highway, 2 episodes of 10 steps."""

from __future__ import annotations

import json

import pytest

from diacc.cli import main
from diacc.experiments.grid import make_cell
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.scorecard import (
    DEFAULT_AGENT,
    REFERENCES,
    REPO_ROOT,
    SUITES,
    ScorecardConfig,
    _playable,
    _settings,
    suite_cells,
)

TINY = ["--suites", "train", "--backends", "highway", "--episodes", "2", "--episode-steps", "10"]


@pytest.fixture(autouse=True)
def _at_repo_root(monkeypatch):
    monkeypatch.chdir(REPO_ROOT)  # the geometry maps and the shipped agent live there


def test_scorecard_of_the_example_controller(tmp_path, capsys):
    out = tmp_path / "card"
    argv = ["scorecard", "--policy", "examples.keep_right_controller:make", *TINY]
    assert main([*argv, "--out", str(out)]) == 0
    card = json.loads((out / "scorecard.json").read_text())
    assert card["policy"] == "examples.keep_right_controller:make" and card["stream"] == "test"
    entries = card["entries"]
    assert [e["metric"] for e in entries] == ["delay", "throughput", "p_sce", "collision"]
    delay = entries[0]
    assert delay["cell"] == "train-50_N25_rho0.40_D1" and delay["n_episodes"] == 2
    assert set(delay["vs"]) == set(REFERENCES)
    assert all(
        v["n_pairs"] == 2 and v["low"] <= v["change"] <= v["high"] for v in delay["vs"].values()
    )
    markdown = (out / "scorecard.md").read_text()
    assert "| highway | train-50_N25_rho0.40_D1 | delay |" in markdown
    assert "2 episodes per cell is a smoke test" in markdown
    for name in ("policy", *REFERENCES):  # every column is a `diacc eval` results directory
        assert (out / "highway" / "train" / name / "episodes.csv").exists()
    before = (out / "scorecard.json").read_bytes()
    assert main([*argv, "--out", str(out)]) == 0  # resumes: nothing to run, the same card
    assert (out / "scorecard.json").read_bytes() == before


def test_the_agent_skips_the_cells_it_cannot_observe():
    """The shipped agent observes at most 40 vehicles: every zero-shot row, not N = 45."""
    cells = suite_cells(SUITES["zero-shot"])
    crowded = make_cell(
        {"map": "train-50", "n_vehicles": 45, "cav_penetration": 0.4, "style_mix": "D1"}
    )
    playable = _playable(PolicySpec(DEFAULT_AGENT), [*cells, crowded], EvalSettings())
    assert len(cells) == 10 and playable == cells
    assert len(suite_cells(SUITES["geometry"])) == 5 and len(suite_cells(SUITES["demand"])) == 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--suites", "train,nowhere"], "unknown suite 'nowhere'"),
        (["--backends", "carla"], "unknown backend 'carla'"),
        (["--episodes", "1"], "--episodes must be >= 2"),
        (["--agent", "missing.pt"], "reference agent missing.pt not found"),
    ],
)
def test_bad_scorecard_options_are_one_line(tmp_path, capsys, extra, message):
    argv = ["scorecard", "--policy", "heuristic", *TINY, *extra, "--out", str(tmp_path / "c")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_scoring_the_shipped_agent_does_not_evaluate_it_twice(tmp_path):
    from diacc.experiments.scorecard import ScorecardConfig, _specs

    agent = ScorecardConfig(PolicySpec(DEFAULT_AGENT), tmp_path)
    assert list(_specs(agent)) == ["policy", "same-mix", "heuristic"]
    sampled = ScorecardConfig(PolicySpec(DEFAULT_AGENT, sampled=True), tmp_path)
    assert list(_specs(sampled)) == ["policy", *REFERENCES]


@pytest.mark.parametrize(
    "checkpoint", sorted(p.name for p in (REPO_ROOT / "checkpoints").glob("*.pt"))
)
def test_every_shipped_agent_gets_a_scorecard(tmp_path, checkpoint):
    """Issue 42: the scorecard runs on every shipped agent (tiny budget, its training cell)."""
    out = tmp_path / "card"
    argv = ["scorecard", "--policy", f"checkpoints/{checkpoint}", *TINY, "--out", str(out)]
    assert main(argv) == 0
    card = json.loads((out / "scorecard.json").read_text())
    delay = next(e for e in card["entries"] if e["metric"] == "delay")
    assert delay["n_episodes"] == 2 and "same-mix" in delay["vs"]
    assert delay["vs"]["same-mix"]["n_pairs"] == 2


def test_the_demand_suite_gives_every_cav_to_the_policy(tmp_path):
    """A controller is scored on the CAVs it drives: no demand CAV is left to drive itself."""
    cfg = ScorecardConfig(PolicySpec("heuristic"), tmp_path)
    for name in SUITES:
        want = "every" if name == "demand" else "own"
        assert _settings(cfg, name, "highway").agent_slots == want, name

"""`diacc scorecard` at a tiny budget: the training suite on highway, 2 episodes of 10 steps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from diacc.cli import main
from diacc.experiments.grid import make_cell
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.scorecard import (
    DEFAULT_AGENT,
    REFERENCES,
    SUITES,
    ScorecardConfig,
    ScorecardError,
    _playable,
    _settings,
    check_config,
    suite_cells,
)
from diacc.sim.scenario import Scenario

#: The repository root: the geometry maps and the shipped agent are read from there.
REPO_ROOT = Path(__file__).resolve().parent.parent
TINY = ["--suites", "train", "--backends", "highway", "--episodes", "2", "--episode-steps", "10"]


@pytest.fixture(autouse=True)
def _at_repo_root(monkeypatch):
    monkeypatch.chdir(REPO_ROOT)  # the geometry maps and the shipped agent live there


#: The settings every hand-built card of these tests carries.
CARD_SETTINGS = {
    "actions": "greedy",
    "episodes_per_cell": 30,
    "stream": "test",
    "episode_steps": 330,
    "psar_horizon": "headway",
    "psar_full_brake": "known",
    "agent": "a.pt",
    "suites": {},
}


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


def test_the_generated_suite_is_the_test_streams_maps_and_the_agent_plays_them():
    """Maps no training or choice may see (the generator's test seeds), every one
    playable by the shipped agent (its road table and vehicle count hold them)."""
    cells = suite_cells(SUITES["generated"])
    assert [c.map for c in cells] == [f"gen-test-{i}" for i in range(20)]
    assert {c.n_vehicles for c in cells} == {25}
    assert _playable(PolicySpec(DEFAULT_AGENT), cells, EvalSettings()) == cells


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
    settings = _settings(cfg, "demand", "highway")
    (cell,) = SUITES["demand"].cells
    own = Scenario(kind="demand", inflow_vph=cell["inflow_vph"], cav_slots=16)  # a cap of 16
    demand = settings.apply_slots(own)
    assert demand.n_slots == demand.n_cavs > own.n_slots == 16


def test_the_summary_counts_better_same_and_worse_cells():
    from diacc.experiments.scorecard import summarise, to_markdown

    def entry(cell, metric, change, measurable, mean=1.0):
        vs = {"change": change, "low": change, "high": change, "n_pairs": 30}
        vs["measurable"] = measurable
        return {
            "suite": "geometry",
            "backend": "sumo",
            "cell": cell,
            "metric": metric,
            "unit": "%",
            "mean": mean,
            "std": 0.0,
            "n_episodes": 30,
            "vs": {"same-mix": vs, "heuristic": None, "diacc": None},
        }

    entries = [
        entry("a", "delay", -20.0, True),  # lower delay: better
        entry("b", "delay", +1.0, False),  # interval holds 0: no measurable difference
        entry("c", "delay", +8.0, True),  # worse
        entry("a", "throughput", -3.0, True),  # lower throughput: worse
        entry("a", "collision", 0.0, False, mean=0.0),
        entry("b", "collision", 0.0, False, mean=3.3),  # one episode of 30 collided
    ]
    (row,) = summarise(entries)
    assert (row["suite"], row["backend"], row["cells"]) == ("geometry", "sumo", 3)
    assert row["delay_vs_same-mix"] == {"better": 1, "same": 1, "worse": 1}
    assert row["throughput_vs_same-mix"] == {"better": 0, "same": 0, "worse": 1}
    assert "delay_vs_heuristic" not in row and row["cells_with_collision"] == 1
    card = {
        "policy": "p",
        **CARD_SETTINGS,
        "summary": [row],
        "entries": [],
        "notes": [],
    }
    assert "| geometry | sumo | 3 | 1 / 1 / 1 | 0 / 0 / 1 | — | 1 |" in to_markdown(card)


# ------------------------------------------------ a recipe's seeds: several --policy (issue 60)
SEEDS = ["scorecard", "--policy", "accelerate", "--policy", "remain", *TINY]


def test_several_policies_are_scored_seed_by_seed_against_references_run_once(
    tmp_path, monkeypatch
):
    import diacc.experiments.scorecard as scorecard

    runs: list[tuple[str, int]] = []  # (results directory, cells it ran)
    real = scorecard.evaluate

    def counting(spec, cells, episodes, out, *args, **kwargs):
        summary = real(spec, cells, episodes, out, *args, **kwargs)
        runs.append((Path(out).name, len(summary.cells_run)))
        return summary

    monkeypatch.setattr(scorecard, "evaluate", counting)
    out = tmp_path / "card"
    assert main([*SEEDS, "--out", str(out)]) == 0
    results = sorted(p.name for p in (out / "highway" / "train").iterdir())
    assert results == sorted(["policy-1", "policy-2", *REFERENCES])  # each reference once
    assert sorted(runs) == sorted((name, 1) for name in results)
    card = json.loads((out / "scorecard.json").read_text())
    assert card["scorecard_version"] == 2 and "entries" not in card
    seeds = card["seeds"]
    assert [(s["results"], s["policy_spec"]) for s in seeds] == [
        ("policy-1", "accelerate"),
        ("policy-2", "remain"),
    ]
    for seed in seeds:  # per seed: today's entries and summary
        assert [e["metric"] for e in seed["entries"]] == list(scorecard.METRICS)
        assert all(e["n_episodes"] == 2 for e in seed["entries"])
        assert seed["summary"] == scorecard.summarise(seed["entries"])
        delay = seed["entries"][0]["vs"]
        assert all(v is not None and v["n_pairs"] == 2 for v in delay.values())
    assert card["agreement"] == scorecard.agreement(seeds)
    (row,) = card["agreement"]
    assert row["seeds"] == 2 and row["delay_vs_same-mix"]["cells"] == 1
    assert sum(row["delay_vs_heuristic"]["better"]) == 1  # one cell, k seeds better
    # the pooled column: both seeds' episodes of the cell, paired by episode seed
    pooled = card["pooled"]["entries"]
    assert [e["metric"] for e in pooled] == list(scorecard.METRICS)
    assert all(e["n_episodes"] == 4 and e["n_seeds"] == 2 for e in pooled)
    assert pooled[0]["vs"]["same-mix"]["n_pairs"] == 2  # pairs are episode seeds
    markdown = (out / "scorecard.md").read_text()
    assert markdown.startswith("# Scorecard: 2 seeds of accelerate, remain (greedy)")
    for line in (
        "## Agreement of the seeds",
        "## Summary: pooled",
        "## Summary: policy-1",
        "## Summary: policy-2",
        "| highway | policy-1 | train-50_N25_rho0.40_D1 | delay |",
        "| highway | policy-2 | train-50_N25_rho0.40_D1 | delay |",
        "| highway | pooled | train-50_N25_rho0.40_D1 | delay |",
    ):
        assert line in markdown, line
    assert "best" not in markdown.replace("none selected", "")  # no seed is singled out
    # resume: nothing left to run for any candidate or reference, the same card
    before = (out / "scorecard.json").read_bytes()
    runs.clear()
    assert main([*SEEDS, "--out", str(out)]) == 0
    assert sorted(runs) == sorted((name, 0) for name in results)
    assert (out / "scorecard.json").read_bytes() == before


def test_the_seeds_agreement_counts_cells_by_how_many_seeds_are_better_or_worse():
    from diacc.experiments.scorecard import agreement, seeds_markdown

    def entry(cell, change, measurable):
        vs = {"change": change, "low": change, "high": change, "n_pairs": 30}
        vs["measurable"] = measurable
        return {
            "suite": "zero-shot",
            "backend": "highway",
            "cell": cell,
            "metric": "delay",
            "unit": "%",
            "mean": 1.0,
            "std": 0.0,
            "n_episodes": 30,
            "vs": {"same-mix": vs, "heuristic": None, "diacc": None},
        }

    # cell a: 3 seeds less delay; b: 2 less, 1 level; c: 1 less, 1 level, 1 more;
    # d: played by two seeds only (left out)
    verdicts = {
        "a": [(-9, True), (-5, True), (-1, True)],
        "b": [(-9, True), (-5, True), (1, False)],
        "c": [(-9, True), (1, False), (4, True)],
        "d": [(-9, True), (-5, True)],
    }
    seeds = [{"results": f"policy-{i + 1}", "entries": [], "summary": []} for i in range(3)]
    for cell, found in verdicts.items():
        for seed, (change, measurable) in zip(seeds, found, strict=False):
            seed["entries"].append(entry(cell, change, measurable))
    (row,) = agreement(seeds)
    assert (row["suite"], row["backend"], row["seeds"]) == ("zero-shot", "highway", 3)
    delay = row["delay_vs_same-mix"]
    assert delay["cells"] == 3 and delay["cells_left_out"] == 1
    assert delay["better"] == [0, 1, 1, 1]  # k = 0, 1, 2, 3 seeds
    assert delay["worse"] == [2, 1, 0, 0]
    assert "delay_vs_heuristic" not in row and "throughput_vs_same-mix" not in row
    for seed in seeds:
        seed.update(policy="diacc", policy_spec=f"runs/r-{seed['results']}/checkpoint.pt")
    card = {
        "scorecard_version": 2,
        **CARD_SETTINGS,
        "seeds": seeds,
        "agreement": [row],
        "pooled": {"summary": [], "entries": []},
        "notes": [],
    }
    markdown = seeds_markdown(card)
    assert "| zero-shot | highway | delay vs same-mix | 3 | 1 / 1 / 1 / 0 | 0 / 0 / 1 / 2 |" in (
        markdown
    )
    assert "better in 3 / 2 / 1 / 0 of 3 seeds" in markdown


def test_two_candidates_that_are_one_policy_are_refused(tmp_path, capsys):
    agent = "checkpoints/diacc-train50-realistic-headway-threat-s1.pt"
    for twice in (["heuristic", "heuristic"], [agent, str(REPO_ROOT / agent)]):
        argv = ["scorecard", *(a for p in twice for a in ("--policy", p)), *TINY]
        assert main([*argv, "--out", str(tmp_path / "c")]) == 2
        err = capsys.readouterr().err
        assert "again: the candidates of a scorecard must be distinct" in err
        assert err.count("\n") == 1 and not (tmp_path / "c").exists()


def test_the_committed_single_policy_scorecard_still_renders():
    """The version-1 layout (one candidate, no scorecard_version) renders as committed."""
    from diacc.experiments.scorecard import to_markdown

    results = REPO_ROOT / "benchmarks/studies/scorecard/results/shipped-threat-s1"
    card = json.loads((results / "scorecard.json").read_text(encoding="utf-8"))
    assert "scorecard_version" not in card
    assert to_markdown(card) == (results / "scorecard.md").read_text(encoding="utf-8")


def test_a_candidate_checkpoint_is_paired_with_the_agent(tmp_path):
    """Both are `diacc` by name: the pairing is by results directory, so a checkpoint other
    than the agent gets its change against DIACC."""
    other = "checkpoints/diacc-train50-realistic-headway-s1.pt"
    out = tmp_path / "card"
    assert main(["scorecard", "--policy", other, *TINY, "--out", str(out)]) == 0
    card = json.loads((out / "scorecard.json").read_text())
    delay = card["entries"][0]
    assert delay["metric"] == "delay" and delay["vs"]["diacc"]["n_pairs"] == 2


def test_a_validation_scorecard_plays_the_validation_streams_maps(tmp_path, capsys):
    """Choosing on `validation` never sees a test map: the generated suite's maps are the
    validation stream's of the same index; shipped maps stay (their seeds change)."""
    cells = suite_cells(SUITES["generated"], "validation")
    assert [c.map for c in cells] == [f"gen-validation-{i}" for i in range(20)]
    assert suite_cells(SUITES["geometry"], "validation") == suite_cells(SUITES["geometry"])
    out = tmp_path / "card"
    argv = ["scorecard", "--policy", "heuristic", *TINY, "--stream", "validation"]
    assert main([*argv, "--out", str(out)]) == 0
    card = json.loads((out / "scorecard.json").read_text())
    assert card["stream"] == "validation"
    assert "of the `validation` seed stream" in (out / "scorecard.md").read_text()
    bad = ScorecardConfig(PolicySpec("heuristic"), tmp_path / "bad", stream="legacy")
    with pytest.raises(ScorecardError, match="unknown stream 'legacy'"):
        check_config(bad)

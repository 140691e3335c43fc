"""The scorecard: one command that puts any controller through the standard suite.

``diacc scorecard --policy X`` evaluates X and three references on every cell of
the chosen suites and backends, on the same seeded traffic (the ``test``
stream), and writes one table and one JSON file a leaderboard can read. The
references are ``same-mix`` (the cell's own vehicles, human drivers in the CAV
slots: what control alone changes), the ``heuristic`` (the simplest sensible
rule) and the shipped DIACC agent. Every change comes paired by episode seed
with its 95 % bootstrap interval (:mod:`diacc.experiments.paired`).

Suites (:data:`SUITES`), all with the settings of README's results (330-step
episodes, PSAR horizon ``headway``, ``full_brake = "known"`` for every policy
with PSAR):

* ``train``: the shipped agent's training cell, ``train-50``, N = 25,
  rho = 0.4, D1, preset ``realistic``;
* ``zero-shot``: the paper's zero-shot rows on ``test-25`` and ``test-50``
  (:data:`~diacc.experiments.grid.PAPER_ZERO_SHOT_ROWS`), ``realistic``;
* ``geometry``: the training traffic on maps never trained on (the two test
  maps and ``benchmarks/maps``' right drop, 3-lane and 5-lane roads; run
  from the repository root);
* ``paper-congestion``: the training cell with the paper's stuck cautious
  drivers;
* ``demand``: ``train-50`` fed at 3600 veh/h (rho = 0.4, D1; the demand
  scenario's default 300 s), ``realistic``, every CAV driven by the policy
  (``--agent-slots every`` of ``diacc eval``: a controller is scored on the CAVs
  it drives, not on CAVs left to drive themselves).

A policy that cannot play a cell (a checkpoint that observes fewer vehicles
than the cell has) skips it, and the scorecard says so; results directories
are ``diacc eval``'s, so an interrupted scorecard resumes where it stopped.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from diacc.errors import DiaccError
from diacc.experiments.evaluate import EvaluationError, evaluate, load_episodes
from diacc.experiments.grid import PAPER_ZERO_SHOT_ROWS, Cell, make_cell
from diacc.experiments.paired import PairedChange
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy, parse_policy
from diacc.experiments.report import Table, change_unit, table_from_results
from diacc.fileio import atomic_write, check_output_file
from diacc.sim.mapgen import generated_names
from diacc.sim.scenario import EVERY_CAV

#: The shipped agent every scorecard compares with.
DEFAULT_AGENT = "checkpoints/diacc-train50-realistic-headway-threat-s1.pt"
#: References, by their results directory's name: same-mix, the heuristic, the agent.
REFERENCES = ("same-mix", "heuristic", "diacc")
#: Metrics of the scorecard (``diacc table`` rows).
METRICS = ("delay", "throughput", "p_sce", "collision")
#: Settings of README's results.
EPISODE_STEPS = 330
PSAR_HORIZON = "headway"
PSAR_FULL_BRAKE = "known"
#: Below this many episodes per cell the scorecard says its intervals are not to be judged by.
FEW_EPISODES = 10
SCORECARD_MD = "scorecard.md"
SCORECARD_JSON = "scorecard.json"
TRAINING_CELL = {"map": "train-50", "n_vehicles": 25, "cav_penetration": 0.4, "style_mix": "D1"}
GEOMETRY_MAPS = (
    "test-50",
    "test-25",
    "benchmarks/maps/right-50.toml",
    "benchmarks/maps/three-lane-right.toml",
    "benchmarks/maps/five-lane-fast.toml",
)
#: Maps of the ``generated`` suite: the first of the generator's ``test`` stream, which
#: no training or choice may use (diacc.sim.mapgen).
GENERATED_MAPS = 20


class ScorecardError(DiaccError, ValueError):
    """Unknown suite or backend, missing reference agent or suite files; one line."""


@dataclass(frozen=True)
class Suite:
    """Cells and HDV style preset of one part of the scorecard."""

    name: str
    cells: tuple[dict, ...]  # cell mappings, as a grid file's [[cells]]
    style_preset: str
    about: str
    agent_slots: int | str = EVERY_CAV  # EvalSettings.agent_slots of its demand cells


SUITES = {
    s.name: s
    for s in (
        Suite("train", (TRAINING_CELL,), "realistic", "the shipped agent's training cell"),
        Suite(
            "zero-shot",
            tuple(
                {"map": m, "n_vehicles": n, "cav_penetration": rho, "style_mix": mix}
                for m in ("test-25", "test-50")
                for n, rho, mix in PAPER_ZERO_SHOT_ROWS
            ),
            "realistic",
            "the paper's zero-shot rows",
        ),
        Suite(
            "geometry",
            tuple({**TRAINING_CELL, "map": m} for m in GEOMETRY_MAPS),
            "realistic",
            "the training traffic on maps never trained on",
        ),
        Suite(
            "generated",
            tuple({**TRAINING_CELL, "map": m} for m in generated_names("test", GENERATED_MAPS)),
            "realistic",
            f"the training traffic on {GENERATED_MAPS} generated maps (test generator seeds)",
        ),
        Suite("paper-congestion", (TRAINING_CELL,), "paper-congestion", "stuck cautious drivers"),
        Suite(
            "demand",
            ({**TRAINING_CELL, "n_vehicles": 1, "inflow_vph": 3600.0},),
            "realistic",
            "3600 veh/h entering train-50, every CAV driven by the policy",
        ),
    )
}


@dataclass(frozen=True)
class ScorecardConfig:
    """What a scorecard evaluates (how much: ``episodes``; where: ``out_dir``)."""

    policy: PolicySpec
    out_dir: Path
    episodes: int = 30
    suites: tuple[str, ...] = tuple(SUITES)
    backends: tuple[str, ...] = ("highway", "sumo")
    agent: str = DEFAULT_AGENT
    episode_steps: int = EPISODE_STEPS
    stream: str = "test"
    workers: int = 1


def suite_cells(suite: Suite) -> list[Cell]:
    """The suite's cells (map paths relative to the repository root, as ``diacc eval``
    takes them from there); one line if the checkout lacks a map file."""
    for values in suite.cells:
        if values["map"].endswith(".toml") and not Path(values["map"]).exists():
            raise ScorecardError(
                f"suite {suite.name} needs {values['map']}: run the scorecard from the root "
                "of a diacc clone (its benchmarks/ folder is not installed)"
            )
    return [make_cell(dict(values), f"suite {suite.name}") for values in suite.cells]


def check_config(cfg: ScorecardConfig) -> None:
    """One-line errors for what would otherwise fail after hours of episodes."""
    unknown = [s for s in cfg.suites if s not in SUITES]
    if unknown or not cfg.suites:
        raise ScorecardError(
            f"unknown suite {(unknown or [''])[0]!r}; use some of {', '.join(SUITES)}"
        )
    if not Path(cfg.agent).exists():
        raise ScorecardError(
            f"reference agent {cfg.agent} not found: run from the repository root or give --agent"
        )
    if cfg.episodes < 2:
        raise ScorecardError(f"--episodes must be >= 2 (intervals need pairs), got {cfg.episodes}")
    _check_agent(cfg.agent)
    for name in (SCORECARD_JSON, SCORECARD_MD):  # written last, after hours of episodes
        check_output_file(cfg.out_dir / name)


def _check_agent(agent: str) -> None:
    """One line unless ``--agent`` is a checkpoint that loads (before any episode: the
    candidate's results would be written before the agent's turn came)."""
    spec = parse_policy(agent)
    if spec.is_baseline or spec.is_scripted or spec.is_python:
        raise ScorecardError(f"--agent {agent} is not a checkpoint; give a checkpoint.pt")
    build_policy(spec)


def _specs(cfg: ScorecardConfig) -> dict[str, PolicySpec]:
    """Results directory name -> policy: the candidate, then the references (the agent
    not twice: scoring the shipped agent itself leaves its "vs DIACC" column empty)."""
    specs = {
        "policy": cfg.policy,
        "same-mix": PolicySpec("same-mix"),
        "heuristic": PolicySpec("heuristic"),
        "diacc": PolicySpec(cfg.agent),
    }
    candidate = cfg.policy
    if not candidate.sampled and Path(candidate.name).resolve() == Path(cfg.agent).resolve():
        del specs["diacc"]
    return specs


def _playable(spec: PolicySpec, cells: list[Cell], settings: EvalSettings) -> list[Cell]:
    """The cells a policy can play (a checkpoint observes at most its ``max_vehicles``)."""
    policy = build_policy(spec)
    playable = []
    for cell in cells:
        try:
            policy.env_config(cell, settings)
        except DiaccError:
            continue
        playable.append(cell)
    return playable


def run_scorecard(cfg: ScorecardConfig, say: Callable[[str], None] = print) -> dict:
    """Evaluate every (suite, backend) and write :data:`SCORECARD_MD` and
    :data:`SCORECARD_JSON` into ``cfg.out_dir``; returns the JSON's content."""
    check_config(cfg)
    suites = {name: suite_cells(SUITES[name]) for name in cfg.suites}
    notes: list[str] = []
    for name, cells in suites.items():
        for backend in cfg.backends:
            settings = _settings(cfg, name, backend)
            for label, spec in _specs(cfg).items():
                playable = _playable(spec, cells, settings)
                for cell in cells:
                    if cell not in playable:
                        notes.append(f"{label} cannot play {name} cell {cell.key} on {backend}")
                if not playable:
                    continue
                out = cfg.out_dir / backend / name / label
                evaluate(spec, playable, cfg.episodes, out, settings, cfg.workers, progress=False)
                say(f"scorecard: {name} on {backend}: {label} done ({len(playable)} cells)")
    card = _collect(cfg, suites, notes)
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(cfg.out_dir / SCORECARD_JSON, (json.dumps(card, indent=2) + "\n").encode())
    atomic_write(cfg.out_dir / SCORECARD_MD, to_markdown(card).encode())
    return card


def _settings(cfg: ScorecardConfig, suite: str, backend: str) -> EvalSettings:
    return EvalSettings(
        backend=backend,
        episode_steps=cfg.episode_steps,
        style_preset=SUITES[suite].style_preset,
        psar_horizon=PSAR_HORIZON,
        psar_full_brake=PSAR_FULL_BRAKE,
        agent_slots=SUITES[suite].agent_slots,
        stream=cfg.stream,
    )


def _change(change: PairedChange | None) -> dict | None:
    if change is None:
        return None
    return {
        "change": change.change,
        "low": change.low,
        "high": change.high,
        "n_pairs": change.n_pairs,
        "measurable": change.measurable,
    }


def _collect(cfg: ScorecardConfig, suites: dict[str, list[Cell]], notes: list[str]) -> dict:
    """The scorecard's JSON: one entry per (suite, backend, cell, metric) of the policy."""
    entries = []
    label = None
    for name, cells in suites.items():
        for backend in cfg.backends:
            dirs = [cfg.out_dir / backend / name / d for d in ("policy", *REFERENCES)]
            loaded = [(d, *load_episodes(d)) for d in dirs if (d / "episodes.csv").exists()]
            if not loaded or loaded[0][0].name != "policy":
                continue
            table = table_from_results(loaded, rows=METRICS)
            column = table.columns[0]
            label = label or table.policy[column]
            refs = {d.name: meta["policy"] for d, meta, _ in loaded[1:]}
            for cell in cells:
                for metric in METRICS:
                    entry = _entry(table, column, cell, metric, refs)
                    if entry is not None:
                        entries.append({"suite": name, "backend": backend, **entry})
    if label is None:
        raise EvaluationError(f"no scorecard results in {cfg.out_dir}")
    return {
        "policy": label,
        "policy_spec": cfg.policy.name,
        "actions": "sampled" if cfg.policy.sampled else "greedy",
        "agent": cfg.agent,
        "stream": cfg.stream,
        "episodes_per_cell": cfg.episodes,
        "episode_steps": cfg.episode_steps,
        "psar_horizon": PSAR_HORIZON,
        "psar_full_brake": PSAR_FULL_BRAKE,
        "suites": {
            n: {"style_preset": SUITES[n].style_preset, "about": SUITES[n].about} for n in suites
        },
        "backends": list(cfg.backends),
        "interval": "95 % percentile bootstrap over episodes paired by seed",
        "summary": summarise(entries),
        "entries": entries,
        "notes": notes,
    }


def _entry(table: Table, column: str, cell: Cell, metric: str, refs: dict[str, str]) -> dict | None:
    """One scorecard entry; ``refs``: reference directory name -> the policy it holds."""
    stat = table.stats.get((cell.key, metric, column))
    if stat is None:
        return None
    versus = {}
    for name in REFERENCES:
        against = dataclasses.replace(table, paired_against=refs[name]) if name in refs else None
        versus[name] = None if against is None else _change(against.paired(cell, metric, column))
    return {
        "cell": cell.key,
        "metric": metric,
        "unit": change_unit(metric),
        "mean": stat.mean,
        "std": stat.std,
        "n_episodes": stat.n_episodes,
        "vs": versus,
    }


#: Metrics the summary counts, and whether a lower value is the better one.
SUMMARY_METRICS = {"delay": True, "throughput": False, "p_sce": True}


def summarise(entries: list[dict]) -> list[dict]:
    """Per (suite, backend): over its cells, how often the policy is measurably better,
    not measurably different (the interval holds 0) or measurably worse than each
    reference, per metric of :data:`SUMMARY_METRICS`, and the cells with a collision."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for e in entries:
        groups.setdefault((e["suite"], e["backend"]), []).append(e)
    summary = []
    for (suite, backend), group in groups.items():
        row = {
            "suite": suite,
            "backend": backend,
            "cells": len({e["cell"] for e in group}),
            "cells_with_collision": sum(e["mean"] > 0 for e in group if e["metric"] == "collision"),
        }
        for metric, lower_is_better in SUMMARY_METRICS.items():
            for ref in REFERENCES:
                counts = {"better": 0, "same": 0, "worse": 0}
                for e in group:
                    change = e["vs"].get(ref) if e["metric"] == metric else None
                    if change is None:
                        continue
                    if not change["measurable"]:
                        counts["same"] += 1
                    elif (change["change"] < 0) == lower_is_better:
                        counts["better"] += 1
                    else:
                        counts["worse"] += 1
                if sum(counts.values()):
                    row[f"{metric}_vs_{ref}"] = counts
        summary.append(row)
    return summary


def _counts(counts: dict | None) -> str:
    if counts is None:
        return "—"
    return f"{counts['better']} / {counts['same']} / {counts['worse']}"


def summary_lines(card: dict) -> list[str]:
    """The summary table: better / no measurable difference / worse, cells per entry
    (columns of references the card compares with)."""
    keys = {key for row in card["summary"] for key in row}
    refs = [r for r in REFERENCES if any(k.endswith(f"_vs_{r}") for k in keys)]
    head = [f"{m} vs {r}" for m in SUMMARY_METRICS for r in refs]
    lines = [
        "## Summary",
        "",
        "Cells where the policy is measurably better / not measurably different / "
        "measurably worse than each reference (paired intervals; lower delay and p(SCE), "
        "higher throughput are better).",
        "",
        "| suite | backend | cells | " + " | ".join(head) + " | cells with a collision |",
        "|---|---|---|" + "---|" * len(head) + "---|",
    ]
    for row in card["summary"]:
        counts = [_counts(row.get(f"{m}_vs_{r}")) for m in SUMMARY_METRICS for r in refs]
        lines.append(
            f"| {row['suite']} | {row['backend']} | {row['cells']} | "
            + " | ".join(counts)
            + f" | {row['cells_with_collision']} |"
        )
    return lines


def _format(change: dict | None, unit: str) -> str:
    if change is None:
        return "—"
    mark = "" if change["measurable"] else "≈ "
    return f"{mark}{change['change']:+.1f} {unit} [{change['low']:+.1f}, {change['high']:+.1f}]"


def to_markdown(card: dict) -> str:
    """The scorecard as Markdown: one table per suite."""
    lines = [
        f"# Scorecard: {card['policy']} ({card['actions']})",
        "",
        f"{card['episodes_per_cell']} episodes per cell of the `{card['stream']}` seed stream, "
        f"{card['episode_steps']}-step episodes, PSAR horizon {card['psar_horizon']}, "
        f"full_brake {card['psar_full_brake']}; changes paired by episode seed with their "
        "95 % bootstrap interval, ≈: no measurable difference (the interval holds 0). "
        f"Agent: `{card['agent']}`.",
    ]
    if card["episodes_per_cell"] < FEW_EPISODES:
        lines += [
            "",
            f"**{card['episodes_per_cell']} episodes per cell is a smoke test**: a percentile "
            f"bootstrap over fewer than {FEW_EPISODES} pairs is too narrow to judge by.",
        ]
    lines += ["", *summary_lines(card)]
    for suite, about in card["suites"].items():
        lines += ["", f"## {suite}: {about['about']} ({about['style_preset']})", ""]
        lines += ["| backend | cell | metric | value | vs same-mix | vs heuristic | vs DIACC |"]
        lines += ["|---|---|---|---|---|---|---|"]
        for e in (e for e in card["entries"] if e["suite"] == suite):
            unit = "%" if e["unit"] == "%" else "pp"
            lines.append(
                f"| {e['backend']} | {e['cell']} | {e['metric']} | {e['mean']:.2f} ± "
                f"{e['std']:.2f} | "
                + " | ".join(_format(e["vs"].get(r), unit) for r in REFERENCES)
                + " |"
            )
    if card["notes"]:
        lines += ["", *(f"- {n}" for n in card["notes"])]
    return "\n".join(lines) + "\n"

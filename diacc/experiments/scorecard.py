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

A recipe is its training seeds, reported seed by seed and never the best alone:
several candidates (``--policy`` repeated) are each scored as one would be, into
``policy-1``, ``policy-2`` ... beside the references, which run once. Their card
(``scorecard_version`` 2; one candidate's has none and keeps the layout of
version 1) holds every seed's entries and summary, the seeds' agreement (per cell,
in how many seeds the change is measurably better / worse: :func:`agreement`) and
a pooled column (every seed's episodes of a cell, paired by episode seed with the
references, the bootstrap resampling the seeds too).
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
from diacc.experiments.report import TRAINING_RUN, Table, change_unit, table_from_results
from diacc.experiments.sametraffic import row_cell
from diacc.fileio import atomic_write, check_output_file
from diacc.sim.mapgen import (
    generated_name,
    generated_names,
    is_generated_name,
    parse_generated_name,
)
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
#: Results directory of a single candidate (several: ``policy-1``, ``policy-2`` ...).
CANDIDATE = "policy"
#: ``scorecard_version`` of a card of several candidates (a card without the field,
#: of one candidate, is version 1: today's single-policy layout).
SEEDS_VERSION = 2
#: Name of the column that pools every candidate's episodes.
POOLED = "pooled"
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
#: Seed streams a scorecard runs on: ``test`` to report, ``validation`` to choose a
#: recipe's checkpoints and seeds on (its episode seeds and generated maps disjoint).
STREAMS = ("test", "validation")


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
            f"the training traffic on {GENERATED_MAPS} generated maps of the card's stream",
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
    """What a scorecard evaluates (how much: ``episodes``; where: ``out_dir``).

    ``policy``: the candidate, or the candidates of a recipe (its training seeds), each
    scored on its own against references evaluated once (:attr:`candidates`).
    """

    policy: PolicySpec | tuple[PolicySpec, ...]
    out_dir: Path
    episodes: int = 30
    suites: tuple[str, ...] = tuple(SUITES)
    backends: tuple[str, ...] = ("highway", "sumo")
    agent: str = DEFAULT_AGENT
    episode_steps: int = EPISODE_STEPS
    stream: str = "test"
    workers: int = 1

    @property
    def candidates(self) -> dict[str, PolicySpec]:
        """Results directory name -> candidate: ``policy`` for one, ``policy-1``,
        ``policy-2`` ... (in the order given) for several."""
        specs = self.policy if isinstance(self.policy, tuple) else (self.policy,)
        if len(specs) == 1:
            return {CANDIDATE: specs[0]}
        return {f"{CANDIDATE}-{i}": spec for i, spec in enumerate(specs, 1)}


def suite_cells(suite: Suite, stream: str = "test") -> list[Cell]:
    """The suite's cells (map paths relative to the repository root, as ``diacc eval``
    takes them from there); one line if the checkout lacks a map file.

    On the ``validation`` stream a generated map is the validation stream's map of the
    same index: a recipe's checkpoints and seeds are chosen on roads as new to it as the
    test stream's, but never on those (diacc.sim.mapgen's streams are disjoint)."""
    for values in suite.cells:
        if values["map"].endswith(".toml") and not Path(values["map"]).exists():
            raise ScorecardError(
                f"suite {suite.name} needs {values['map']}: run the scorecard from the root "
                "of a diacc clone (its benchmarks/ folder is not installed)"
            )
    return [
        make_cell({**values, "map": _on_stream(values["map"], stream)}, f"suite {suite.name}")
        for values in suite.cells
    ]


def _on_stream(map_name: str, stream: str) -> str:
    """A generated map's counterpart on ``stream``; any other map itself."""
    if not is_generated_name(map_name):
        return map_name
    _, index = parse_generated_name(map_name)
    return generated_name(stream, index)


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
    if cfg.stream not in STREAMS:
        raise ScorecardError(f"unknown stream {cfg.stream!r}; use {' or '.join(STREAMS)}")
    if cfg.episodes < 2:
        raise ScorecardError(f"--episodes must be >= 2 (intervals need pairs), got {cfg.episodes}")
    _check_distinct(list(cfg.candidates.values()))
    _check_agent(cfg.agent)
    for name in (SCORECARD_JSON, SCORECARD_MD):  # written last, after hours of episodes
        check_output_file(cfg.out_dir / name)


def _identity(spec: PolicySpec) -> tuple[str, bool]:
    """What a candidate resolves to: a checkpoint's file, else its name; and its actions."""
    path = Path(spec.name)
    name = str(path.resolve()) if path.is_file() else spec.name
    return name, spec.sampled


def _check_distinct(specs: list[PolicySpec]) -> None:
    """One line if two candidates resolve to the same policy (a recipe's seeds are
    distinct runs; the same one twice would count its cells twice)."""
    if not specs:
        raise ScorecardError("give at least one --policy")
    seen: dict[tuple[str, bool], int] = {}
    for i, spec in enumerate(specs):
        first = seen.setdefault(_identity(spec), i)
        if first != i:
            raise ScorecardError(
                f"--policy {spec.name} is --policy {specs[first].name} again: the candidates "
                "of a scorecard must be distinct policies (the seeds of a recipe)"
            )


def _is_agent(spec: PolicySpec, agent: str) -> bool:
    """Whether a candidate is the reference agent itself (its greedy actions)."""
    return not spec.sampled and Path(spec.name).resolve() == Path(agent).resolve()


def _check_agent(agent: str) -> None:
    """One line unless ``--agent`` is a checkpoint that loads (before any episode: the
    candidate's results would be written before the agent's turn came)."""
    spec = parse_policy(agent)
    if spec.is_baseline or spec.is_scripted or spec.is_python:
        raise ScorecardError(f"--agent {agent} is not a checkpoint; give a checkpoint.pt")
    build_policy(spec)


def _specs(cfg: ScorecardConfig) -> dict[str, PolicySpec]:
    """Results directory name -> policy: the candidates, then the references, each once
    (the agent not twice: scoring the shipped agent alone leaves its "vs DIACC" column
    empty; among several candidates, the agent's own has no "vs DIACC")."""
    specs = {
        **cfg.candidates,
        "same-mix": PolicySpec("same-mix"),
        "heuristic": PolicySpec("heuristic"),
        "diacc": PolicySpec(cfg.agent),
    }
    candidates = list(cfg.candidates.values())
    if len(candidates) == 1 and _is_agent(candidates[0], cfg.agent):
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
    suites = {name: suite_cells(SUITES[name], cfg.stream) for name in cfg.suites}
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


Loaded = list[tuple[Path, dict, list[dict[str, str]]]]


def _load(directory: Path) -> Loaded:
    return [(directory, *load_episodes(directory))] if (directory / "episodes.csv").exists() else []


def _references(cfg: ScorecardConfig, where: Path, with_agent: bool) -> Loaded:
    """The references' results of one (suite, backend); the agent's only if ``with_agent``."""
    names = REFERENCES if with_agent else tuple(r for r in REFERENCES if r != "diacc")
    return [column for name in names for column in _load(where / name)]


def _entries(loaded: Loaded, suite: str, backend: str, cells: list[Cell]) -> tuple[str, list[dict]]:
    """The candidate's (``loaded[0]``) label and entries in one (suite, backend), paired
    with each reference's column (by its column, not its policy name: a candidate
    checkpoint and the agent share the name ``diacc``)."""
    table = table_from_results(loaded, rows=METRICS)
    column = table.columns[0]
    refs = {d.name: table.columns[i] for i, (d, _, _) in enumerate(loaded) if i > 0}
    entries = []
    for cell in cells:
        for metric in METRICS:
            entry = _entry(table, column, cell, metric, refs)
            if entry is not None:
                entries.append({"suite": suite, "backend": backend, **entry})
    return table.policy[column], entries


def _candidate(
    cfg: ScorecardConfig, suites: dict[str, list[Cell]], name: str, spec: PolicySpec
) -> tuple[str | None, list[dict]]:
    """One candidate's label (None: no results) and entries over every (suite, backend)."""
    label, entries = None, []
    with_agent = not _is_agent(spec, cfg.agent)
    for suite, cells in suites.items():
        for backend in cfg.backends:
            where = cfg.out_dir / backend / suite
            mine = _load(where / name)
            if not mine:
                continue
            found, more = _entries(
                [*mine, *_references(cfg, where, with_agent)], suite, backend, cells
            )
            label = label or found
            entries += more
    return label, entries


def _pooled(cfg: ScorecardConfig, suites: dict[str, list[Cell]]) -> list[dict]:
    """Entries of a column pooling every candidate's episodes per cell, paired by episode
    seed with the references (the bootstrap resamples the seeds' runs too:
    :mod:`diacc.experiments.paired`); no "vs DIACC" where a candidate is the agent."""
    with_agent = not any(_is_agent(s, cfg.agent) for s in cfg.candidates.values())
    entries = []
    for suite, cells in suites.items():
        for backend in cfg.backends:
            where = cfg.out_dir / backend / suite
            rows: list[dict[str, str]] = []
            metas: list[dict] = []
            played: dict[str, set[int]] = {}  # cell -> the candidates that played it
            for run, name in enumerate(cfg.candidates):
                for _, meta, seed_rows in _load(where / name):
                    rows += [{**r, TRAINING_RUN: str(run)} for r in seed_rows]
                    metas.append(meta)
                    for r in seed_rows:
                        played.setdefault(row_cell(r), set()).add(run)
            if not rows:
                continue
            meta = {k: v for k, v in metas[0].items() if k != "checkpoint"}
            pooled = [(Path(POOLED), {**meta, "policy": POOLED}, rows)]
            _, found = _entries(
                [*pooled, *_references(cfg, where, with_agent)], suite, backend, cells
            )
            entries += [{**e, "n_seeds": len(played.get(e["cell"], ()))} for e in found]
    return entries


def _collect(cfg: ScorecardConfig, suites: dict[str, list[Cell]], notes: list[str]) -> dict:
    """The scorecard's JSON: one entry per (suite, backend, cell, metric) of the policy;
    of several candidates, per candidate, their agreement and their pooled episodes."""
    shared = {
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
    }
    seeds = []
    for name, spec in cfg.candidates.items():
        label, entries = _candidate(cfg, suites, name, spec)
        if label is None:
            raise EvaluationError(
                f"no scorecard results of {spec.name} in {cfg.out_dir / '*' / '*' / name}"
            )
        seeds.append(
            {
                "results": name,
                "policy": label,
                "policy_spec": spec.name,
                "summary": summarise(entries),
                "entries": entries,
            }
        )
    actions = "sampled" if next(iter(cfg.candidates.values())).sampled else "greedy"
    if len(seeds) == 1:  # version 1: one candidate's card, as before several were taken
        (one,) = seeds
        return {
            "policy": one["policy"],
            "policy_spec": one["policy_spec"],
            "actions": actions,
            **shared,
            "summary": one["summary"],
            "entries": one["entries"],
            "notes": notes,
        }
    pooled = _pooled(cfg, suites)
    return {
        "scorecard_version": SEEDS_VERSION,
        "actions": actions,
        **shared,
        "seeds": seeds,
        "agreement": agreement(seeds),
        "pooled": {"summary": summarise(pooled), "entries": pooled},
        "notes": notes,
    }


def _entry(table: Table, column: str, cell: Cell, metric: str, refs: dict[str, str]) -> dict | None:
    """One scorecard entry; ``refs``: reference directory name -> its column of ``table``."""
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


def _verdict(change: dict, lower_is_better: bool) -> str:
    """``better``, ``same`` (the interval holds 0) or ``worse`` of one paired change."""
    if not change["measurable"]:
        return "same"
    return "better" if (change["change"] < 0) == lower_is_better else "worse"


def _groups(entries: list[dict]) -> dict[tuple[str, str], list[dict]]:
    groups: dict[tuple[str, str], list[dict]] = {}
    for e in entries:
        groups.setdefault((e["suite"], e["backend"]), []).append(e)
    return groups


def summarise(entries: list[dict]) -> list[dict]:
    """Per (suite, backend): over its cells, how often the policy is measurably better,
    not measurably different (the interval holds 0) or measurably worse than each
    reference, per metric of :data:`SUMMARY_METRICS`, and the cells with a collision."""
    summary = []
    for (suite, backend), group in _groups(entries).items():
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
                    if change is not None:
                        counts[_verdict(change, lower_is_better)] += 1
                if sum(counts.values()):
                    row[f"{metric}_vs_{ref}"] = counts
        summary.append(row)
    return summary


def agreement(seeds: list[dict]) -> list[dict]:
    """Per (suite, backend), from the candidates' own entries: for each metric of
    :data:`SUMMARY_METRICS` and reference, ``better[k]`` (``worse[k]``) = the cells in
    which exactly k of the candidates are measurably better (worse), k = 0 .. seeds,
    over the ``cells`` every candidate was compared in (a cell a candidate could not
    play, or lacks a comparison in, is left out and counted in ``cells_left_out``)."""
    n = len(seeds)
    verdicts: dict[tuple[str, str], dict[tuple[str, str, str], list[str]]] = {}
    cells: dict[tuple[str, str], dict[str, None]] = {}  # every cell any candidate played
    for seed in seeds:
        for (suite, backend), group in _groups(seed["entries"]).items():
            found = verdicts.setdefault((suite, backend), {})
            cells.setdefault((suite, backend), {}).update(dict.fromkeys(e["cell"] for e in group))
            for e in group:
                lower_is_better = SUMMARY_METRICS.get(e["metric"])
                if lower_is_better is None:
                    continue
                for ref in REFERENCES:
                    change = e["vs"].get(ref)
                    if change is not None:
                        key = (e["cell"], e["metric"], ref)
                        found.setdefault(key, []).append(_verdict(change, lower_is_better))
    rows = []
    for (suite, backend), found in verdicts.items():
        row: dict = {"suite": suite, "backend": backend, "seeds": n}
        for metric in SUMMARY_METRICS:
            for ref in REFERENCES:
                everyone = [found.get((cell, metric, ref), []) for cell in cells[(suite, backend)]]
                complete = [v for v in everyone if len(v) == n]
                if not complete:
                    continue
                row[f"{metric}_vs_{ref}"] = {
                    "cells": len(complete),
                    "cells_left_out": len(everyone) - len(complete),
                    "better": [sum(v.count("better") == k for v in complete) for k in range(n + 1)],
                    "worse": [sum(v.count("worse") == k for v in complete) for k in range(n + 1)],
                }
        rows.append(row)
    return rows


def _counts(counts: dict | None) -> str:
    if counts is None:
        return "—"
    return f"{counts['better']} / {counts['same']} / {counts['worse']}"


def _refs(rows: list[dict]) -> list[str]:
    """The references a summary's rows compare with, in :data:`REFERENCES` order."""
    keys = {key for row in rows for key in row}
    return [r for r in REFERENCES if any(k.endswith(f"_vs_{r}") for k in keys)]


def summary_lines(
    card: dict, summary: list[dict] | None = None, title: str = "Summary", who: str = "the policy"
) -> list[str]:
    """The summary table: better / no measurable difference / worse, cells per entry
    (columns of references the card compares with); ``summary``: another than the
    card's own (a candidate's, the pooled one), under ``title``, of ``who``."""
    rows = card["summary"] if summary is None else summary
    refs = _refs(rows)
    head = [f"{m} vs {r}" for m in SUMMARY_METRICS for r in refs]
    lines = [
        f"## {title}",
        "",
        f"Cells where {who} is measurably better / not measurably different / "
        "measurably worse than each reference (paired intervals; lower delay and p(SCE), "
        "higher throughput are better).",
        "",
        "| suite | backend | cells | " + " | ".join(head) + " | cells with a collision |",
        "|---|---|---|" + "---|" * len(head) + "---|",
    ]
    for row in rows:
        counts = [_counts(row.get(f"{m}_vs_{r}")) for m in SUMMARY_METRICS for r in refs]
        lines.append(
            f"| {row['suite']} | {row['backend']} | {row['cells']} | "
            + " | ".join(counts)
            + f" | {row['cells_with_collision']} |"
        )
    return lines


_REF_NAMES = {"same-mix": "same-mix", "heuristic": "the heuristic", "diacc": "DIACC"}


def agreement_lines(card: dict) -> list[str]:
    """The seeds' agreement: per (suite, backend) and comparison, in how many cells
    k of the n seeds are measurably better, and measurably worse (k = n .. 0)."""
    n = len(card["seeds"])
    ks = " / ".join(str(k) for k in range(n, -1, -1))
    lines = [
        "## Agreement of the seeds",
        "",
        f"Cells in which k of the {n} seeds are measurably better, and measurably worse, "
        f"than each reference (k = {ks}), from each seed's own paired intervals; over the "
        "cells every seed was compared in. No seed is selected: a recipe is all of them.",
        "",
        f"| suite | backend | comparison | cells | better in {ks} of {n} seeds "
        f"| worse in {ks} of {n} seeds |",
        "|---|---|---|---|---|---|",
    ]
    for row in card["agreement"]:
        for metric in SUMMARY_METRICS:
            for ref in REFERENCES:
                found = row.get(f"{metric}_vs_{ref}")
                if found is None:
                    continue
                better = " / ".join(str(c) for c in reversed(found["better"]))
                worse = " / ".join(str(c) for c in reversed(found["worse"]))
                lines.append(
                    f"| {row['suite']} | {row['backend']} | {metric} vs {_REF_NAMES[ref]} | "
                    f"{found['cells']} | {better} | {worse} |"
                )
    return lines


def _format(change: dict | None, unit: str) -> str:
    if change is None:
        return "—"
    mark = "" if change["measurable"] else "≈ "
    return f"{mark}{change['change']:+.1f} {unit} [{change['low']:+.1f}, {change['high']:+.1f}]"


def _settings_lines(card: dict, title: str) -> list[str]:
    lines = [
        f"# Scorecard: {title} ({card['actions']})",
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
    return lines


def _entry_row(e: dict, first: str) -> str:
    unit = "%" if e["unit"] == "%" else "pp"
    return (
        f"| {first}{e['cell']} | {e['metric']} | {e['mean']:.2f} ± {e['std']:.2f} | "
        + " | ".join(_format(e["vs"].get(r), unit) for r in REFERENCES)
        + " |"
    )


def to_markdown(card: dict) -> str:
    """The scorecard as Markdown: one table per suite (a card of several candidates:
    :func:`seeds_markdown`)."""
    if card.get("scorecard_version", 1) >= SEEDS_VERSION:
        return seeds_markdown(card)
    lines = _settings_lines(card, card["policy"])
    lines += ["", *summary_lines(card)]
    for suite, about in card["suites"].items():
        lines += ["", f"## {suite}: {about['about']} ({about['style_preset']})", ""]
        lines += ["| backend | cell | metric | value | vs same-mix | vs heuristic | vs DIACC |"]
        lines += ["|---|---|---|---|---|---|---|"]
        for e in (e for e in card["entries"] if e["suite"] == suite):
            lines.append(_entry_row(e, f"{e['backend']} | "))
    if card["notes"]:
        lines += ["", *(f"- {n}" for n in card["notes"])]
    return "\n".join(lines) + "\n"


def seeds_markdown(card: dict) -> str:
    """A card of several candidates (a recipe's seeds): the seeds' agreement, the pooled
    summary, each seed's summary, and one table per suite with every seed's entries and
    the pooled one side by side."""
    seeds = card["seeds"]
    labels = ", ".join(dict.fromkeys(s["policy"] for s in seeds))
    lines = _settings_lines(card, f"{len(seeds)} seeds of {labels}")
    lines += [
        "",
        "Every seed is reported, none selected; `pooled` pools every seed's episodes of a "
        "cell, paired by episode seed with the references (its interval resamples the "
        "seeds too). Seeds:",
        "",
        *(f"- `{s['results']}`: `{s['policy_spec']}` ({s['policy']})" for s in seeds),
    ]
    lines += ["", *agreement_lines(card)]
    pooled = card["pooled"]
    lines += ["", *summary_lines(card, pooled["summary"], "Summary: pooled", "the pooled column")]
    for s in seeds:
        title = f"Summary: {s['results']}"
        lines += ["", *summary_lines(card, s["summary"], title, f"`{s['policy_spec']}`")]
    order: dict[tuple[str, str, str, str], list[tuple[str, dict]]] = {}
    for name, entries in [
        *((s["results"], s["entries"]) for s in seeds),
        (POOLED, pooled["entries"]),
    ]:
        for e in entries:
            key = (e["suite"], e["backend"], e["cell"], e["metric"])
            order.setdefault(key, []).append((name, e))
    for suite, about in card["suites"].items():
        lines += ["", f"## {suite}: {about['about']} ({about['style_preset']})", ""]
        lines += [
            "| backend | seed | cell | metric | value | vs same-mix | vs heuristic | vs DIACC |"
        ]
        lines += ["|---|---|---|---|---|---|---|---|"]
        for key, found in order.items():
            if key[0] == suite:
                lines += [_entry_row(e, f"{e['backend']} | {name} | ") for name, e in found]
    if card["notes"]:
        lines += ["", *(f"- {n}" for n in card["notes"])]
    return "\n".join(lines) + "\n"

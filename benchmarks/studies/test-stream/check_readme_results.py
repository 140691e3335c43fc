"""README's results tables, regenerated from the committed result files (issue 42).

README's "Results in brief" quotes two tables:

* the main table (and docs/results/test-stream.md's first table): per backend
  and policy, the delay per vehicle, the throughput, p(SCE) and the delay's
  change against same-mix with its 95 % interval, recomputed from the committed
  episodes (``benchmarks/studies/test-stream/results/<backend>/<policy>/episodes.csv``)
  with ``diacc table``'s own code;
* the scorecard table: the shipped agent's delay against same-mix on each
  suite of ``diacc scorecard`` (maps never trained on, the paper's zero-shot
  rows, stuck drivers, demand), read from the committed
  ``benchmarks/studies/scorecard/results/shipped-threat-s1/scorecard.json``.

and the figures README and docs/results quote in their prose (issue 57): each number
is regenerated from the committed files and must stand *in its sentence* (or its
table row), beside the words that say what it is (backend, reference, stream,
the heuristic), not merely somewhere on the page:

* README's paper paragraph (the shipped agent against pure HDV and same-mix; the
  1 M-step and 25 % map runs against same-mix, mappo-iadm and the heuristic,
  ``benchmarks/studies/paper-convergence/compare.py``'s pooled changes);
* README's demand bullets and figures: the agents' and the heuristic's changes
  against same-mix and every collision count of the committed demand episodes;
* docs/results/paper-vs-ours.md rows 1-3, 9 and 11 (the numbers it can regenerate);
* docs/results/demand-training.md's every-CAV tables, row by row;
* docs/results/scorecard.md's summary table.

The script writes the rows and claims the pages should hold and compares: it prints
each that differs or is missing and exits 1 if any does. It re-simulates nothing
(seconds); ``tests/test_readme_results.py`` runs it in CI.

    python benchmarks/studies/test-stream/check_readme_results.py          # check README.md
    python benchmarks/studies/test-stream/check_readme_results.py --print  # the rows it should hold
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from diacc.experiments.flowplot import capacity, load_flow
from diacc.experiments.report import build_table, to_csv
from diacc.experiments.scorecard import summary_lines

ROOT = Path(__file__).resolve().parents[3]
RESULTS = Path(__file__).resolve().parent / "results"
#: README row label -> the results directory of each backend and the policy name in the table.
ROWS = {
    "pure HDV": ("pure-hdv", "pure-hdv"),
    "same-mix": ("same-mix", "same-mix"),
    "cooperative (CACC CAVs)": ("cooperative", "cooperative"),
    "heuristic (20-line script under PSAR)": ("heuristic", "heuristic"),
    "**DIACC greedy**": ("diacc-greedy", "diacc"),
    "**DIACC sampled**": ("diacc-sampled", "diacc (sampled)"),
}
BACKENDS = ("highway", "sumo")
HEADER = "| policy | highway | sumo (transfer) |"
SCORECARD = ROOT / "benchmarks/studies/scorecard/results/shipped-threat-s1/scorecard.json"
SCORECARD_HEADER = (
    "| scorecard suite: cell | highway: delay vs same-mix | sumo: delay vs same-mix |"
)
TRAINING_CELL = "train-50_N25_rho0.40_D1"
DEMAND_CELL = "train-50_Q3600_rho0.40_D1"
#: README label of each geometry cell of the scorecard (maps never trained on).
GEOMETRY_LABELS = {
    "test-50": "test-50 (4 -> 2 lanes at 850 m)",
    "test-25": "test-25 (4 -> 3 lanes at 850 m)",
    "benchmarks/maps/right-50.toml": "train-50 with its right lanes ending",
    "benchmarks/maps/three-lane-right.toml": "3 -> 2 lanes, right lane ends, 22 m/s",
    "benchmarks/maps/five-lane-fast.toml": "5 -> 3 lanes, 30 m/s",
}


def table_values(backend: str) -> dict[tuple[str, str], dict[str, str]]:
    """(metric, policy) -> the CSV row of ``diacc table`` over the committed episodes."""
    dirs = [str(RESULTS / backend / directory) for directory, _ in ROWS.values()]
    text = to_csv(build_table(dirs, "episodes", ("delay", "throughput", "p_sce")))
    return {(row["metric"], row["policy"]): row for row in csv.DictReader(io.StringIO(text))}


def cell(values: dict, policy: str) -> str:
    """One backend's entry of a README row: delay (change [interval]) / throughput / p(SCE)."""
    delay = values[("delay", policy)]
    text = f"{float(delay['mean']):.2f}"
    if delay["paired_change"]:  # paired with same-mix, the table's default reference
        change, low, high = (float(delay[k]) for k in ("paired_change", "ci_low", "ci_high"))
        mark = "" if delay["measurable"] == "1" else "≈ "
        text += f" ({mark}{change:.1f} % [{low:.1f}, {high:.1f}])"
    throughput = float(values[("throughput", policy)]["mean"])
    p_sce = float(values[("p_sce", policy)]["mean"])
    return f"{text} / {throughput:.0f} / {p_sce:.1f}"


def expected_rows() -> list[str]:
    tables = {backend: table_values(backend) for backend in BACKENDS}
    rows = []
    for label, (_, policy) in ROWS.items():
        entries = [cell(tables[backend], policy) for backend in BACKENDS]
        if label.startswith("**"):  # README bolds the agents' entries
            entries = [f"**{entry}**" for entry in entries]
        rows.append(f"| {label} | {entries[0]} | {entries[1]} |")
    return rows


def _interval(change: dict) -> str:
    mark = "" if change["measurable"] else "≈ "
    return f"{mark}{change['change']:+.1f} % [{change['low']:+.1f}, {change['high']:+.1f}]"


def _counts(counts: dict) -> str:
    return f"less on {counts['better']}, ≈ on {counts['same']}, more on {counts['worse']}"


def scorecard_rows() -> list[str]:
    """README's scorecard table: delay against same-mix per suite cell, both backends."""
    card = json.loads(SCORECARD.read_text(encoding="utf-8"))
    delay = {
        (e["suite"], e["backend"], e["cell"]): e["vs"]["same-mix"]
        for e in card["entries"]
        if e["metric"] == "delay"
    }
    summary = {(r["suite"], r["backend"]): r for r in card["summary"]}

    def row(label: str, suite: str, cell: str) -> str:
        entries = [_interval(delay[(suite, b, cell)]) for b in BACKENDS]
        return f"| {label} | {entries[0]} | {entries[1]} |"

    rows = []
    for path, label in GEOMETRY_LABELS.items():
        rows.append(row(f"geometry: {label}", "geometry", f"{path}_N25_rho0.40_D1"))
    cells = [summary[("zero-shot", b)] for b in BACKENDS]
    counts = [_counts(c["delay_vs_same-mix"]) for c in cells]
    rows.append(f"| zero-shot: the paper's {cells[0]['cells']} rows | {counts[0]} | {counts[1]} |")
    rows.append(row("paper-congestion: stuck drivers", "paper-congestion", TRAINING_CELL))
    rows.append(row("demand: 3600 veh/h, every CAV the agent's", "demand", DEMAND_CELL))
    return rows


@dataclass(frozen=True)
class Claim:
    """A number as a page writes it, and the words that must share its sentence (prose)
    or its clause of a table row (``row``: the row starting with that text)."""

    value: str
    context: tuple[str, ...] = ()
    row: str | None = None


def _pct(change, unit: str = "%") -> str:
    """``-67.7 % [-71.1, -63.4]``, marked ``≈`` where the interval holds 0."""
    mark = "" if change.measurable else "≈ "
    return f"{mark}{change.change:+.1f} {unit} [{change.low:+.1f}, {change.high:+.1f}]"


def _paired(dirs: list[Path], column: int, against: str, metric: str):
    table = build_table([str(d) for d in dirs], rows=(metric,), paired_against=against)
    return table.paired(table.cells[0], metric, table.columns[column])


def _paired_text(dirs: list[Path], column: int, against: str, metric: str) -> str:
    """The change of ``dirs[column]`` against ``against`` (a policy or one of ``dirs``)
    with its interval, as README writes it ("-67.7 % [-71.1, -63.4]")."""
    return _pct(_paired(dirs, column, against, metric))


PAPER = ROOT / "benchmarks/studies/paper-vs-ours/results/train"


def _paper_speed(backend: str, map_name: str, against: str) -> str:
    """The shipped agent's speed change against ``against`` on a training cell, source A."""
    dirs = [str(PAPER / backend / d) for d in ("pure-hdv", "same-mix", "diacc-greedy")]
    text = to_csv(build_table(dirs, rows=("speed",), paired_against=against))
    row = next(
        r
        for r in csv.DictReader(io.StringIO(text))
        if r["map"] == map_name and r["policy"] == "diacc"
    )
    change, low, high = (float(row[k]) for k in ("paired_change", "ci_low", "ci_high"))
    mark = "" if row["measurable"] == "1" else "≈ "
    return f"{mark}{change:+.1f} % [{low:+.1f}, {high:+.1f}]"


def paper_claims() -> list[str]:
    """README's "Against the paper" figures: the agent's speed change on SUMO at 50 %
    (``paper-congestion``) against pure HDV and against same-mix, with their intervals."""
    return [_paper_speed("sumo", "train-50", a) for a in ("pure-hdv", "same-mix")]


CONVERGENCE = ROOT / "benchmarks/studies/paper-convergence/results"


def convergence(study: str, backend: str, column: str, against: str, metric: str = "delay"):
    """``compare.py``'s pooled change (3 seeds) of a learned column against another
    column on the study's training cell."""
    sys.path.insert(0, str(CONVERGENCE.parent))
    import compare  # benchmarks/studies/paper-convergence/compare.py

    loaded, _ = compare.columns(CONVERGENCE / study / "eval" / backend)
    table = compare.table_from_results(loaded, rows=(metric, "collision"))
    cell = next(c for c in table.cells if c.map.startswith("train"))
    table.paired_against = against
    return table.paired(cell, metric, column)


def paper_paragraph_claims() -> list[Claim]:
    """README's paragraph "Against the paper", each number beside what it compares."""
    a_pure, a_same = paper_claims()
    claims = [
        Claim(a_pure, ("`paper-congestion`", "`test`", "SUMO", "pure HDV", "speed")),
        Claim(a_same, ("`test`", "SUMO", "same vehicles")),
    ]
    one_m = ("1 M steps", "`test`", "same-mix", "mappo-iadm", "heuristic")
    for study in ("paper-congestion", "realistic"):
        for backend in BACKENDS:
            for against in ("same-mix", "heuristic"):
                change = _pct(convergence(study, backend, "diacc", against))
                claims.append(
                    Claim(change.lstrip("-+≈ ") if against == "same-mix" else change, one_m)
                )
    quarter = ("25 % map", "`test`", "heuristic", "same-mix", "mappo-iadm")
    study = "paper-congestion-train-25"
    column = "diacc@train-25"
    claims += [
        Claim(_pct(convergence(study, "sumo", column, "pure-hdv", "speed")), quarter),
        Claim(_pct(convergence(study, "sumo", column, "same-mix")).lstrip("-+"), quarter),
        Claim(
            _pct(convergence(study, "highway", column, "mappo-iadm@train-25")).lstrip("+"), quarter
        ),
        *(Claim(_pct(convergence(study, b, column, "heuristic")), quarter) for b in BACKENDS),
    ]
    return claims


FLOW = ROOT / "benchmarks/studies/demand-training/results"
SCORECARD_PAGE = ROOT / "docs/results/scorecard.md"


def crashed(results_dir: Path) -> tuple[int, int]:
    """(episodes with a collision, episodes) of a committed results directory."""
    with (results_dir / "episodes.csv").open(encoding="utf-8", newline="") as f:
        rows = list(csv.DictReader(f))
    return sum(float(r["collision"] or 0) > 0 for r in rows), len(rows)


def demand_claims() -> list[str]:
    """README's demand figures: the 3:1 agent given every CAV (delay at 3600 veh/h,
    throughput at 4800), driving 16 CAVs (delay at 3600), and the fine-tuned seeds
    against it (delay at 3600, highway), each against same-mix on the same seeds."""
    return [c.value for c in demand_sentence_claims()] + capacity_claims()


def demand_sentence_claims() -> list[Claim]:
    """README's demand bullets, each number in its sentence: the agent's and the
    heuristic's changes against same-mix and every collision count."""
    every, own = FLOW / "flow-every-cav", FLOW / "flow"
    agent = "release-3to1-s3"
    given_every = ("every CAV", "same-mix", "heuristic", "3600 veh/h", "highway", "SUMO")
    claims = []
    for policy in (agent, "heuristic"):
        for backend in BACKENDS:
            dirs = [own / backend / "same-mix/q3600", every / backend / policy / "q3600"]
            claims.append(Claim(_paired_text(dirs, 1, "same-mix", "delay"), given_every))
    quiet = [crashed(every / b / agent / "q3600") for b in BACKENDS]
    if not any(k for k, _ in quiet):
        claims.append(Claim(f"no collision in {quiet[0][1]} episodes", given_every))
    above = ("At 4800 veh/h", "same-mix", "heuristic", "highway", "SUMO")
    for policy in (agent, "heuristic"):
        for backend in BACKENDS:
            dirs = [every / backend / "same-mix/q4800", every / backend / policy / "q4800"]
            claims.append(Claim(_paired_text(dirs, 1, "same-mix", "throughput"), above))
    k, n = crashed(every / "sumo" / agent / "q4800")
    claims.append(Claim(f"a collision in {k} of {n} SUMO episodes", above))
    k, n = crashed(every / "sumo/heuristic/q4800")
    claims.append(Claim(f"the heuristic: {k} of {n} SUMO episodes", above))
    sixteen = ("16 CAVs", "same-mix", "heuristic", "16 slots", "3600 veh/h")
    for policy in (agent, "heuristic"):
        dirs = [own / "highway/same-mix/q3600", own / "highway" / policy / "q3600"]
        claims.append(Claim(_paired_text(dirs, 1, "same-mix", "delay"), sixteen))
    k, n = crashed(own / "sumo" / agent / "q3600")
    claims.append(Claim(f"crashed in {k} of {n} episodes at 3600 veh/h", sixteen + ("SUMO",)))
    tuned = ("Fine-tuned on demand", "every CAV", "their source", "heuristic", "4800 veh/h")
    source = every / "highway" / agent / "q3600"
    for seed in (1, 2):
        dirs = [source, every / "highway" / f"demand-ft-s{seed}/q3600"]
        change = _paired_text(dirs, 1, str(source), "delay")
        claims.append(Claim(change.split(" [")[0].lstrip("-"), tuned))  # "26.5 %": "less time"
    for seed in (1, 2, 3):
        dirs = [own / "highway/same-mix/q3600", every / "highway" / f"demand-ft-s{seed}/q3600"]
        claims.append(Claim(_paired_text(dirs, 1, "same-mix", "delay").split(" [")[0], tuned))
    for backend, name in (("highway", "highway"), ("sumo", "SUMO")):
        counts = {s: crashed(every / backend / f"demand-ft-s{s}/q4800") for s in (1, 2, 3)}
        hit = [s for s, (k, _) in counts.items() if k]
        if not hit:
            continue
        k, n = counts[hit[0]]
        if len(hit) == 3 and len(set(counts.values())) == 1:
            claims.append(Claim(f"each seed crashed in {k} of {n} {name} episodes", tuned))
        else:
            seeds = " and ".join(map(str, hit))
            claims.append(Claim(f"seeds {seeds} in {k} of {n} {name} episodes", tuned))
    return claims


def capacity_claims() -> list[str]:
    """README's pure-HDV capacity of each backend on the demand road (its largest mean
    outflow over the inflows of the committed flow results), to the nearest 100 veh/h."""
    points = load_flow([FLOW / "flow"])
    names = {"highway": "highway", "sumo": "SUMO"}
    return [f"~{round(capacity(points, b)[0], -2):,.0f} veh/h on {names[b]}" for b in BACKENDS]


def figure_claims() -> list[Claim]:
    """README's sentences on the flow figures: every crashed point they mark."""
    claims = []
    own = FLOW / "flow/sumo/release-3to1-s3/q3600"
    k, n = crashed(own)
    context = ("16 CAVs", "`test`", "heuristic", "crashed point")
    claims.append(Claim(f"the release agent's on SUMO at 3600 veh/h ({k} of {n}", context))
    every = FLOW / "flow-every-cav"
    k, n = crashed(every / "sumo/release-3to1-s3/q4800")
    context = ("Every CAV driven", "`test`", "crashed episodes", "4800 veh/h")
    claims.append(Claim(f"release agent in {k} of {n} SUMO episodes", context))
    counts = {crashed(every / b / "demand-ft-s1/q4800") for b in BACKENDS}
    if len(counts) == 1:
        k, n = counts.pop()
        claims.append(Claim(f"demand-trained s1 in {k} of {n} on each simulator", context))
    return claims


def paper_vs_ours_claims() -> list[Claim]:
    """docs/results/paper-vs-ours.md: the numbers of rows 1-3, 9 and 11 that the
    committed files regenerate, each in its row and clause."""
    claims = [
        Claim(_paper_speed("sumo", "train-50", "pure-hdv"), ("SUMO",), row="| 1 |"),
        Claim(_paper_speed("highway", "train-50", "pure-hdv"), ("highway",), row="| 1 |"),
        Claim(_paper_speed("sumo", "train-50", "same-mix"), ("SUMO",), row="| 2 |"),
        Claim(_paper_speed("sumo", "train-25", "pure-hdv"), ("SUMO",), row="| 3 |"),
        Claim(_paper_speed("highway", "train-25", "pure-hdv"), ("highway",), row="| 3 |"),
        Claim(
            _paper_speed("highway", "train-25", "same-mix"), ("highway", "same-mix"), row="| 3 |"
        ),
    ]
    study, column = "paper-congestion-train-25", "diacc@train-25"
    for backend, name in (("sumo", "SUMO"), ("highway", "highway")):
        speed = _pct(convergence(study, backend, column, "pure-hdv", "speed"))
        claims.append(Claim(speed, (name, "vs same-mix"), row="| 3 |"))
        heuristic = _pct(convergence(study, backend, column, "heuristic", "speed"))
        claims.append(Claim(f"{heuristic} {name}", ("heuristic",), row="| 3 |"))
    same = [_pct(convergence("paper-congestion", b, "diacc", "same-mix")) for b in BACKENDS]
    claims.append(Claim(f"diacc {same[0]} / {same[1]}", ("against same-mix",), row="| 9 |"))
    level = [_pct(convergence("paper-congestion", b, "diacc", "mappo-iadm")) for b in BACKENDS]
    claims += [Claim(f"{level[0]} (highway), {level[1]} (SUMO)", ("mappo-iadm",), row="| 9 |")]
    # row 11: every evaluation episode with a collision under PSAR in source D
    small = ROOT / "benchmarks/studies/reproduce-small/results"
    for actions in ("greedy", "sampled"):
        for run in sorted((small / actions / "eval").glob("*/*-s[0-9]")):
            if "nopsar" in run.name or run.name.startswith("mappo-train"):
                continue  # the variants without PSAR: every training cell collides
            k, n = crashed(run)
            if k:
                variant, seed = run.name.rsplit("-train-", 1)[0], run.name.rsplit("-s", 1)[1]
                words = (f"{variant} seed {seed}", actions, "in D (")
                claims.append(
                    Claim(f"{k} of {n} {run.parent.name.upper()} episodes", words, row="| 11 |")
                )
    return claims


#: The every-CAV tables of docs/results/demand-training.md: the line above each table,
#: and its row labels -> the series' results folder name.
DEMAND_TABLES = {
    "Highway, 3600 veh/h:": ("highway", "q3600"),
    "Highway, 4800 veh/h:": ("highway", "q4800"),
    "SUMO, 3600 veh/h (the agents were trained on highway only):": ("sumo", "q3600"),
    "SUMO, 4800 veh/h:": ("sumo", "q4800"),
}
DEMAND_ROWS = {
    "same-mix": "same-mix",
    "heuristic (every CAV)": "heuristic",
    "release agent (3:1 s3)": "release-3to1-s3",
    "demand-trained s1": "demand-ft-s1",
    "demand-trained s2": "demand-ft-s2",
    "demand-trained s3": "demand-ft-s3",
}
DEMAND_PAGE = ROOT / "docs/results/demand-training.md"


def demand_table_rows(backend: str, inflow: str) -> list[str]:
    """One every-CAV table of the demand-training page: delay, throughput, p(SCE) and
    their changes against same-mix, and the collision episodes, per policy."""
    every = FLOW / "flow-every-cav" / backend
    same = every / "same-mix" / inflow
    if not same.is_dir():  # 3600 veh/h: slots do not change same-mix
        same = FLOW / "flow" / backend / "same-mix" / inflow
    dirs = [same] + [every / d / inflow for d in list(DEMAND_ROWS.values())[1:]]
    metrics = ("delay", "throughput", "p_sce")
    table = build_table([str(d) for d in dirs], rows=metrics, paired_against=str(same))
    cell = table.cells[0]
    rows = []
    for label, column, path in zip(DEMAND_ROWS, table.columns, dirs, strict=True):
        entries = []
        for metric, digits in zip(metrics, (1, 0, 1), strict=True):
            text = f"{table.stats[(cell.key, metric, column)].mean:.{digits}f}"
            change = table.paired(cell, metric, column) if path != same else None
            if change is not None:
                mark = "" if change.measurable else "≈ "
                text += f" ({mark}{change.change:+.1f} [{change.low:+.1f}, {change.high:+.1f}])"
            entries.append(text)
        k, n = crashed(path)
        rows.append(f"| {label} | {' | '.join(entries)} | {k} of {n} |")
    return rows


def _units(text: str) -> list[str]:
    """The sentences of a page's prose, whitespace collapsed (lines wrap anywhere):
    paragraphs and list items split at a sentence's end."""
    blocks = re.split(r"\n\s*\n|\n(?=\s*- )", text)
    units = []
    for block in blocks:
        flat = " ".join(block.split())
        units += re.split(r"(?<=[.!?])\s+(?=[A-Z*(\[`])", flat)
    return units


def _row_units(text: str, prefix: str) -> list[str]:
    """The clauses of a table row's cells (split at "; ")."""
    line = next((ln for ln in text.splitlines() if ln.startswith(prefix)), "")
    return [c for cell in line.split(" | ") for c in cell.split("; ")]


def check_claims(page: Path, claims: list[Claim], kind: str) -> bool:
    """Print each claim as found in its sentence (row clause) or MISSING; True if all are."""
    text = page.read_text(encoding="utf-8")
    prose = _units(text)
    ok = True
    for claim in claims:
        units = _row_units(text, claim.row) if claim.row else prose
        found = any(claim.value in u and all(w in u for w in claim.context) for u in units)
        ok &= found
        where = f"row {claim.row.strip('| ')}" if claim.row else "its sentence"
        words = f" with {', '.join(claim.context)}" if claim.context else ""
        state = "found" if found else "MISSING"
        print(f"{page.name}'s {kind} claim {claim.value!r} in {where}{words}: {state}")
    return ok


def readme_rows(readme: Path, header: str = HEADER) -> list[str]:
    lines = readme.read_text(encoding="utf-8").splitlines()
    if header not in lines:
        sys.exit(f"check_readme_results: {readme} has no line {header!r}")
    start = lines.index(header) + 2  # past the header and its rule
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append(line)
    return rows


def scorecard_heuristic_claims() -> list[Claim]:
    """README's sentence on the scorecard against the heuristic: per suite, the cells
    where the agent's delay is measurably less / level / more, highway and SUMO."""
    card = json.loads(SCORECARD.read_text(encoding="utf-8"))
    summary = {(r["suite"], r["backend"]): r["delay_vs_heuristic"] for r in card["summary"]}
    labels = {
        "train": "training cell",
        "geometry": "maps never trained on",
        "zero-shot": "the paper's zero-shot rows",
        "paper-congestion": "stuck drivers",
        "demand": "demand",
    }
    context = ("Against the heuristic", "scorecard's summary", "highway", "SUMO")
    claims = []
    for suite, label in labels.items():
        counts = [summary[(suite, b)] for b in BACKENDS]
        text = " and ".join(f"{c['better']} / {c['same']} / {c['worse']}" for c in counts)
        claims.append(Claim(f"{label} {text}", context))
    return claims


#: The shipped generalist's scorecard (issue 60), one directory per backend.
GENERALIST = {
    "highway": ROOT / "benchmarks/studies/scorecard/results/suite-s3",
    "sumo": ROOT / "benchmarks/studies/scorecard/results/suite-s3-sumo",
}
#: The suites of the scorecard before `generated` (18 cells per backend).
CURRENT_SUITES = ("train", "zero-shot", "geometry", "paper-congestion", "demand")


def _suite_change(backend: str, suite: str, reference: str) -> float:
    """The change (%) of the generalist's mean delay over a suite against a reference,
    every episode paired with the reference's of the same cell and seed."""
    key = ("map", "n_vehicles", "cav_penetration", "style_mix", "inflow_vph", "seed")

    def delays(column: str) -> dict[tuple[str, ...], float]:
        path = GENERALIST[backend] / backend / suite / column / "episodes.csv"
        with path.open(newline="") as f:
            return {
                tuple(r[k] for k in key): float(r["delay_per_vehicle_s"]) for r in csv.DictReader(f)
            }

    mine, ref = delays("policy"), delays(reference)
    both = sorted(set(mine) & set(ref))
    return (sum(mine[k] for k in both) / sum(ref[k] for k in both) - 1) * 100


def generalist_claims() -> list[Claim]:
    """README's paragraph on the recommended agent: per backend the 18 scorecard cells
    where its delay is measurably less / level / more than the heuristic's, its suite
    means against the heuristic on highway, the training cell's change, its collisions."""
    cards = {
        b: json.loads((d / "scorecard.json").read_text(encoding="utf-8"))
        for b, d in GENERALIST.items()
    }
    claims = []
    for backend, card in cards.items():
        rows = [r for r in card["summary"] if r["suite"] in CURRENT_SUITES]
        counts = [
            sum(r["delay_vs_heuristic"][k] for r in rows) for k in ("better", "same", "worse")
        ]
        cells = sum(r["cells"] for r in rows)
        text = " / ".join(map(str, counts))
        name = "SUMO" if backend == "sumo" else backend
        claims.append(Claim(f"{text} of the scorecard's {cells} {name} cells", ("heuristic",)))
    labels = {
        "zero-shot": "on the paper's zero-shot rows",
        "geometry": "on the maps never trained on",
        "demand": "on the demand road",
        "generated": "on the 20 generated test maps",
    }
    for suite, label in labels.items():
        change = _suite_change("highway", suite, "heuristic")
        claims.append(Claim(f"{change:+.1f} % {label}", ("heuristic",)))
    (train,) = [
        e["vs"]["heuristic"]
        for e in cards["highway"]["entries"]
        if e["suite"] == "train" and e["metric"] == "delay"
    ]
    claims.append(Claim(f"{_interval(train)} on the training cell", ("heuristic",)))
    episodes = crashes = 0
    for path in (GENERALIST["highway"] / "highway").glob("*/policy/episodes.csv"):
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        episodes += len(rows)
        crashes += sum(int(float(r["collision"])) for r in rows)
    if crashes == 0:
        claims.append(Claim(f"no collision in any of its {episodes:,} highway card episodes"))
    else:
        claims.append(Claim(f"a collision in {crashes} of its {episodes:,} highway card episodes"))
    return claims


def readme_claims() -> list[tuple[str, list[Claim]]]:
    """Every prose claim of README, by kind."""
    capacity = ("pure HDV's capacity", "`test`")
    return [
        ("paper", paper_paragraph_claims()),
        ("scorecard", scorecard_heuristic_claims()),
        ("generalist", generalist_claims()),
        ("demand", demand_sentence_claims()),
        ("figure", figure_claims() + [Claim(c, capacity) for c in capacity_claims()]),
    ]


def check_table(name: str, page: Path, header: str, want: list[str]) -> bool:
    have = readme_rows(page, header)
    bad = [(w, h) for w, h in zip(want, have + [""] * len(want), strict=False) if w != h]
    for w, h in bad:
        print(f"page:     {h}\nresults:  {w}")
    if len(have) != len(want):
        print(f"the {name} table has {len(have)} rows, the results {len(want)}")
    ok = not bad and len(have) == len(want)
    print(f"the {name} table: {'matches' if ok else 'DIFFERS from'} the committed results")
    return ok


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--readme", type=Path, default=ROOT / "README.md")
    p.add_argument("--docs", type=Path, default=ROOT / "docs/results", help="docs/results")
    p.add_argument("--print", action="store_true", help="print the expected rows and exit")
    args = p.parse_args(argv)
    tables = {"main": (HEADER, expected_rows()), "scorecard": (SCORECARD_HEADER, scorecard_rows())}
    demand_page = args.docs / DEMAND_PAGE.name
    demand_tables = {title: demand_table_rows(*where) for title, where in DEMAND_TABLES.items()}
    if args.print:
        for header, want in tables.values():
            print("\n".join([header, *want]), end="\n\n")
        for title, want in demand_tables.items():
            print("\n".join([f"demand-training.md, {title}", *want]), end="\n\n")
        for kind, claims in readme_claims() + [("paper-vs-ours", paper_vs_ours_claims())]:
            print(f"{kind} claims:", ", ".join(c.value for c in claims))
        return 0
    ok = True
    for kind, claims in readme_claims():
        ok &= check_claims(args.readme, claims, kind)
    ok &= check_claims(args.docs / "paper-vs-ours.md", paper_vs_ours_claims(), "row")
    for name, (header, want) in tables.items():
        ok &= check_table(name, args.readme, header, want)
    summary = summary_lines(json.loads(SCORECARD.read_text(encoding="utf-8")))
    ok &= check_table(
        "docs/results/scorecard.md summary",
        args.docs / SCORECARD_PAGE.name,
        summary[4],
        summary[6:],
    )
    text = demand_page.read_text(encoding="utf-8").splitlines()
    for title, want in demand_tables.items():
        if title not in text:
            print(f"{demand_page}: no line {title!r}")
            ok = False
            continue
        at = text.index(title)
        header = next(ln for ln in text[at:] if ln.startswith("|"))
        section = "\n".join(text[at:])
        page = _Section(section)
        ok &= check_table(f"demand-training.md {title}", page, header, want)
    return 0 if ok else 1


class _Section:
    """A page's text from one line on, read as ``readme_rows`` reads a file."""

    def __init__(self, text: str) -> None:
        self.text = text

    def read_text(self, encoding: str = "utf-8") -> str:
        return self.text


if __name__ == "__main__":
    sys.exit(main())

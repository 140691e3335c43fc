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

The script writes the rows README should hold and compares: it prints each row
that differs and exits 1 if any does. It re-simulates nothing (seconds);
``tests/test_readme_results.py`` runs it in CI.

    python benchmarks/studies/test-stream/check_readme_results.py          # check README.md
    python benchmarks/studies/test-stream/check_readme_results.py --print  # the rows it should hold
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
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


PAPER = ROOT / "benchmarks/studies/paper-vs-ours/results/train/sumo"


def paper_claims() -> list[str]:
    """README's "Against the paper" figures: the agent's speed change on SUMO at 50 %
    (``paper-congestion``) against pure HDV and against same-mix, with their intervals."""
    dirs = [str(PAPER / d) for d in ("pure-hdv", "same-mix", "diacc-greedy")]
    claims = []
    for against in ("pure-hdv", "same-mix"):
        text = to_csv(build_table(dirs, rows=("speed",), paired_against=against))
        row = next(
            r
            for r in csv.DictReader(io.StringIO(text))
            if r["map"] == "train-50" and r["policy"] == "diacc"
        )
        change, low, high = (float(row[k]) for k in ("paired_change", "ci_low", "ci_high"))
        claims.append(f"{change:+.1f} % [{low:+.1f}, {high:+.1f}]")
    return claims


FLOW = ROOT / "benchmarks/studies/demand-training/results"
SCORECARD_PAGE = ROOT / "docs/results/scorecard.md"


def _paired_text(dirs: list[Path], column: int, against: str, metric: str) -> str:
    """The change of ``dirs[column]`` against ``against`` (a policy or one of ``dirs``)
    with its interval, as README writes it ("-67.7 % [-71.1, -63.4]")."""
    table = build_table([str(d) for d in dirs], rows=(metric,), paired_against=against)
    change = table.paired(table.cells[0], metric, table.columns[column])
    return f"{change.change:+.1f} % [{change.low:+.1f}, {change.high:+.1f}]"


def demand_claims() -> list[str]:
    """README's demand figures: the 3:1 agent given every CAV (delay at 3600 veh/h,
    throughput at 4800), driving 16 CAVs (delay at 3600), and the fine-tuned seeds
    against it (delay at 3600, highway), each against same-mix on the same seeds."""
    every, own = FLOW / "flow-every-cav", FLOW / "flow"
    agent = "release-3to1-s3"
    claims = []
    for backend in BACKENDS:
        dirs = [own / backend / "same-mix/q3600", every / backend / agent / "q3600"]
        claims.append(_paired_text(dirs, 1, "same-mix", "delay"))
    for backend in BACKENDS:
        dirs = [every / backend / "same-mix/q4800", every / backend / agent / "q4800"]
        claims.append(_paired_text(dirs, 1, "same-mix", "throughput"))
    dirs = [own / "highway/same-mix/q3600", own / "highway" / agent / "q3600"]
    claims.append(_paired_text(dirs, 1, "same-mix", "delay"))
    source = every / "highway" / agent / "q3600"
    for seed in (1, 2):
        tuned = every / "highway" / f"demand-ft-s{seed}/q3600"
        change = _paired_text([source, tuned], 1, str(source), "delay")
        claims.append(change.split(" [")[0].lstrip("-"))  # "26.5 %": "less time than"
    return claims + capacity_claims()


def capacity_claims() -> list[str]:
    """README's pure-HDV capacity of each backend on the demand road (its largest mean
    outflow over the inflows of the committed flow results), to the nearest 100 veh/h."""
    points = load_flow([FLOW / "flow"])
    names = {"highway": "highway", "sumo": "SUMO"}
    return [f"~{round(capacity(points, b)[0], -2):,.0f} veh/h on {names[b]}" for b in BACKENDS]


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--readme", type=Path, default=ROOT / "README.md")
    p.add_argument("--print", action="store_true", help="print the expected rows and exit")
    args = p.parse_args(argv)
    tables = {"main": (HEADER, expected_rows()), "scorecard": (SCORECARD_HEADER, scorecard_rows())}
    if args.print:
        for header, want in tables.values():
            print("\n".join([header, *want]), end="\n\n")
        print("paper claims:", ", ".join(paper_claims()))
        print("demand claims:", ", ".join(demand_claims()))
        return 0
    failed = False
    text = " ".join(args.readme.read_text(encoding="utf-8").split())  # lines wrap anywhere
    for kind, claims in (("paper", paper_claims()), ("demand", demand_claims())):
        for claim in claims:
            found = claim in text
            failed |= not found
            print(f"README's {kind} claim {claim}: {'found' if found else 'MISSING'}")
    summary = summary_lines(json.loads(SCORECARD.read_text(encoding="utf-8")))
    pages = {name: (args.readme, header, want) for name, (header, want) in tables.items()}
    pages["docs/results/scorecard.md summary"] = (SCORECARD_PAGE, summary[4], summary[6:])
    for name, (page, header, want) in pages.items():
        have = readme_rows(page, header)
        bad = [(w, h) for w, h in zip(want, have + [""] * len(want), strict=False) if w != h]
        for w, h in bad:
            print(f"README:   {h}\nresults:  {w}")
        if len(have) != len(want):
            print(f"the {name} table has {len(have)} rows, the results {len(want)}")
        ok = not bad and len(have) == len(want)
        failed |= not ok
        print(f"the {name} table: {'matches' if ok else 'DIFFERS from'} the committed results")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

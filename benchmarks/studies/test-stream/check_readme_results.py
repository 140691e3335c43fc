"""README's main results table, regenerated from the committed result files (issue 42).

README's "Results in brief" table (and docs/results/test-stream.md's first
table) quote, per backend and policy, the delay per vehicle, the throughput,
p(SCE) and the delay's change against same-mix with its 95 % interval. This
script recomputes every one of those numbers from the committed episodes
(``benchmarks/studies/test-stream/results/<backend>/<policy>/episodes.csv``) with
``diacc table``'s own code, writes the row README should hold, and compares:
it prints each row that differs and exits 1 if any does. It re-simulates
nothing (seconds); ``tests/test_readme_results.py`` runs it in CI.

    python benchmarks/studies/test-stream/check_readme_results.py          # check README.md
    python benchmarks/studies/test-stream/check_readme_results.py --print  # the rows it should hold
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

from diacc.experiments.report import build_table, to_csv

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


def readme_rows(readme: Path) -> list[str]:
    lines = readme.read_text(encoding="utf-8").splitlines()
    if HEADER not in lines:
        sys.exit(f"check_readme_results: {readme} has no line {HEADER!r}")
    start = lines.index(HEADER) + 2  # past the header and its rule
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
    want = expected_rows()
    if args.print:
        print("\n".join(want))
        return 0
    have = readme_rows(args.readme)
    bad = [(w, h) for w, h in zip(want, have + [""] * len(want), strict=False) if w != h]
    for w, h in bad:
        print(f"README:   {h}\nresults:  {w}")
    if len(have) != len(want):
        print(f"README's table has {len(have)} rows, the results {len(want)}")
    ok = not bad and len(have) == len(want)
    print(f"README's main table: {'matches' if ok else 'DIFFERS from'} the committed results")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

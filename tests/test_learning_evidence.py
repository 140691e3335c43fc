"""benchmarks/studies/learning-evidence/analyse.py on committed evaluations: the target
checks per group (seed means) and per seed, which can disagree (one failed seed among good ones)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "benchmarks" / "studies" / "learning-evidence"
SHARE = STUDY / "results" / "train50-train25-3to1" / "eval"


def _rows(out: Path) -> dict[tuple[str, str], list[str]]:
    """{(section, policy): cells} of evaluation.md."""
    rows, section = {}, ""
    for line in (out / "evaluation.md").read_text().splitlines():
        if line.startswith("## "):
            section = line[3:]
        elif line.startswith("| ") and not line.startswith("| policy"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[(section, cells[0])] = cells
    return rows


def test_seed_means_and_seeds_meeting_every_target(tmp_path):
    subprocess.run(
        [sys.executable, str(STUDY / "analyse.py"), str(SHARE),
         "--out", str(tmp_path)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    rows = _rows(tmp_path)
    greedy_hw = rows[("highway, train-50", "share diacc (greedy)")]
    greedy_sumo = rows[("sumo, train-50", "share diacc (greedy)")]
    # Seed 1 stalls under greedy actions: the seed means miss, four seeds alone meet all
    # (seed 5 misses the 20 %).
    assert greedy_hw[-2].startswith("missed: delay >= 20 % below same-mix")
    assert greedy_hw[-1] == "4 of 6 (s2, s3, s4, s6)"
    # On SUMO seed 3's greedy p(SCE) (0.068) is above same-mix's (0.044), seeds 4 and 6
    # are behind the heuristic.
    assert greedy_sumo[-1] == "1 of 6 (s2)"
    assert rows[("highway, train-50", "same-mix")][-1] == ""  # baselines are not checked
    assert (tmp_path / "evaluation.csv").stat().st_size > 0

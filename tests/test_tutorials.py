"""Run every tutorial end to end, in order, and check the figures it promises.

Each tutorial runs as its own Python process (as a user would run it, and so
that libsumo, torch threads and matplotlib state never leak between them),
with ``DIACC_TUTORIAL_OUT`` pointing at a temporary folder that all tutorials
share: tutorial 7 reuses the checkpoint of tutorial 6 there. A separate test
runs tutorial 7 in an empty folder, where it must train its own tiny agent.

They run cell by cell (``docs/tutorial_outputs.py``, as Jupyter would run the
notebook), so that the same run checks the outputs cached for the docs site in
``docs/tutorials-output/``: each cell must print what its page shows and write
the figures shown there (``python docs/tutorial_outputs.py`` rewrites them).
"""

from __future__ import annotations

import sys
from pathlib import Path

import imageio.v2 as imageio
import matplotlib.image as mpimg
import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
TUTORIALS_DIR = REPO / "tutorials"
sys.path.insert(0, str(REPO / "docs"))
import tutorial_outputs  # noqa: E402  (docs/tutorial_outputs.py: no diacc import)

#: Tutorial file -> files (relative to DIACC_TUTORIAL_OUT) it must produce.
EXPECTED: dict[str, tuple[str, ...]] = {
    "01_bottleneck.py": (
        "01_bottleneck/speed_time_space.png",
        "01_bottleneck/frame_step35.png",
    ),
    "02_styles_and_backends.py": (
        "02_styles_and_backends/styles_headway.png",
        "02_styles_and_backends/backends_speed.png",
    ),
    "03_what_a_cav_sees.py": ("03_what_a_cav_sees/cav_neighbour_graphs.png",),
    "04_safety_first.py": ("04_safety_first/psar_cases.png", "04_safety_first/psar_rule_map.png"),
    "05_rewards.py": ("05_rewards/softmin_and_schedule.png", "05_rewards/reward_terms.png"),
    "06_train.py": (
        "06_train/run/checkpoint.pt",
        "06_train/run/progress.jsonl",
        "06_train/curves.png",
        "06_train/diagnostics.png",
        "06_train/speeds.png",
        "06_train/table.md",
    ),
    "07_validate_on_sumo.py": (
        "07_validate_on_sumo/speeds.png",
        "07_validate_on_sumo/sumo_episode.gif",
        "07_validate_on_sumo/sumo_last_frame.png",
    ),
    "08_trained_agent_in_python.py": ("08_trained_agent_in_python/trained_agent_frame.png",),
}


def test_every_tutorial_is_listed() -> None:
    """A new tutorial must be added here (and to tutorials/README.md)."""
    on_disk = sorted(p.name for p in TUTORIALS_DIR.glob("[0-9][0-9]_*.py"))
    assert on_disk == sorted(EXPECTED)
    readme = (TUTORIALS_DIR / "README.md").read_text()
    for name in on_disk:
        assert name in readme, f"{name} missing from tutorials/README.md"


def run_tutorial(name: str, out_dir: Path) -> tutorial_outputs.TutorialRun:
    """Run it in its own process, cwd and DIACC_TUTORIAL_OUT = out_dir, MPLBACKEND=Agg."""
    try:
        return tutorial_outputs.run_cells(name, out_dir, timeout=600)
    except RuntimeError as error:
        pytest.fail(str(error))


def check_outputs(name: str, out_dir: Path) -> None:
    for rel in EXPECTED[name]:
        path = out_dir / rel
        assert path.is_file() and path.stat().st_size > 0, f"{name} did not write {rel}"
        if path.suffix == ".png":
            image = mpimg.imread(path)  # (H, W, 3 or 4)
            assert image.ndim == 3 and min(image.shape[:2]) >= 50, f"{rel}: {image.shape}"
            assert float(image[..., :3].std()) > 0.01, f"{rel} is a blank image"
        if path.suffix == ".gif":
            frames = imageio.mimread(path)
            assert len(frames) >= 2, f"{rel} has {len(frames)} frame(s)"
            assert any(not np.array_equal(frames[0], f) for f in frames[1:]), f"{rel} is a still"


@pytest.fixture(scope="module")
def shared_out(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("tutorial_out")


@pytest.mark.parametrize("name", list(EXPECTED))  # dict order = tutorial order
def test_tutorial_runs(name: str, shared_out: Path) -> None:
    proc = run_tutorial(name, shared_out)
    check_outputs(name, shared_out)
    stale = tutorial_outputs.differences(proc)
    assert not stale, (
        f"the outputs of tutorials/{name} cached for the docs site are out of date; "
        f"regenerate them with `{tutorial_outputs.REGENERATE}` and commit "
        f"docs/tutorials-output/:\n  " + "\n  ".join(stale)
    )
    if name == "06_train.py":
        table = (shared_out / "06_train/table.md").read_text()
        for column in ("pure-hdv", "[untrained]", "[trained]"):
            assert column in table
    if name == "07_validate_on_sumo.py":
        assert "reusing the checkpoint of tutorial 6" in proc.stdout
    if name == "08_trained_agent_in_python.py":
        assert "mean_speed_mps" in proc.stdout and "sampled" in proc.stdout


def test_tutorial_7_alone_trains_its_own_agent(tmp_path: Path) -> None:
    proc = run_tutorial("07_validate_on_sumo.py", tmp_path)
    check_outputs("07_validate_on_sumo.py", tmp_path)
    assert "trained a tiny agent" in proc.stdout
    assert (tmp_path / "07_validate_on_sumo/run/checkpoint.pt").is_file()
    assert not (tmp_path / "06_train").exists()

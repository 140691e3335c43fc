"""Shipped maps and checkpoints are package data (diacc/shipped.py): found through
importlib.resources, one copy in the repository, every file packaged; ``python -m diacc``.

The wheel itself, installed outside the clone, is tested by .ci/wheel_smoke.sh.
"""

from __future__ import annotations

import os
import subprocess
import sys
from fnmatch import fnmatch
from pathlib import Path

import pytest

import diacc
from diacc.experiments.policies import PolicyError, parse_policy
from diacc.shipped import ShippedDataError, require_dir, shipped_checkpoint, shipped_checkpoints
from diacc.sim.maps import MAPS_DIR, MapError, available_maps, load_map
from diacc.tomlfile import read_toml

REPO = Path(__file__).resolve().parent.parent
AGENT = "diacc-train50-realistic-headway-threat-s1.pt"


@pytest.mark.parametrize("kind", ["maps", "checkpoints"])
def test_package_data_is_a_link_to_the_top_level_folder(kind):
    # One copy: contributors edit maps/ and checkpoints/, the package sees the same files.
    link = REPO / "diacc" / "data" / kind
    assert link.is_symlink() and os.readlink(link) == f"../../{kind}"
    assert link.resolve() == (REPO / kind).resolve()


def test_every_shipped_file_is_package_data():
    # A file the patterns miss would be in a clone and not in a wheel.
    setuptools = read_toml(REPO / "pyproject.toml", ValueError)["tool"]["setuptools"]
    patterns = setuptools["package-data"]["diacc"]
    for kind, suffix in (("maps", ".toml"), ("checkpoints", ".pt")):
        files = [f"data/{kind}/{p.name}" for p in (REPO / kind).iterdir() if p.suffix == suffix]
        assert files and all(any(fnmatch(f, pat) for pat in patterns) for f in files), kind


def test_the_folders_come_from_the_installed_package():
    assert MAPS_DIR == Path(diacc.__file__).parent / "data" / "maps"
    assert diacc.CHECKPOINTS_DIR == Path(diacc.__file__).parent / "data" / "checkpoints"
    assert available_maps() == sorted(p.stem for p in (REPO / "maps").glob("*.toml"))
    assert shipped_checkpoints() == sorted(p.name for p in (REPO / "checkpoints").glob("*.pt"))


def test_maps_by_name_from_any_directory_and_by_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load_map("train-25").name == "train-25"
    own = tmp_path / "mine.toml"
    own.write_text((REPO / "maps" / "train-50.toml").read_text())
    assert load_map(own).segments == load_map("train-50").segments
    with pytest.raises(MapError, match="unknown map 'nope'; shipped maps: test-25, "):
        load_map("nope")


def test_a_missing_data_folder_is_one_line():
    with pytest.raises(ShippedDataError, match=r"^the shipped nope folder .* symbolic links"):
        require_dir("nope")


def test_a_shipped_agent_by_name_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = diacc.CHECKPOINTS_DIR / AGENT
    assert shipped_checkpoint(AGENT) == shipped == shipped_checkpoint(AGENT.removesuffix(".pt"))
    assert parse_policy(AGENT.removesuffix(".pt")).name == str(shipped)
    assert diacc.load_policy(AGENT).path == shipped
    # A name with a folder part is a path; a file in the working directory wins.
    assert shipped_checkpoint(f"elsewhere/{AGENT}") is None
    with pytest.raises(PolicyError, match=f"checkpoint elsewhere/{AGENT} does not exist"):
        parse_policy(f"elsewhere/{AGENT}")
    (tmp_path / AGENT).write_bytes(shipped.read_bytes())
    assert parse_policy(AGENT).name == AGENT
    with pytest.raises(PolicyError, match=r"a shipped checkpoint \(diacc-\S+\.pt, diacc-"):
        parse_policy("nope")


def test_python_m_diacc_is_the_diacc_command(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = [sys.executable, "-m", "diacc", "simulate", "--map", "nope"]
    out = subprocess.run(run, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    assert out.returncode == 2
    assert out.stderr.startswith("diacc: error: unknown map 'nope'; shipped maps: test-25")

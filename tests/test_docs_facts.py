"""Counts and versions in README and docs/ agree with the tree (issue 42): none is typed
from memory. Dated measurements (timings, results) are not counts: they carry their
date and command where they stand."""

from __future__ import annotations

import re
from pathlib import Path

from packaging.specifiers import SpecifierSet  # a dependency of pytest

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
README = (REPO / "README.md").read_text(encoding="utf-8")
GETTING_STARTED = (REPO / "docs" / "getting-started.md").read_text(encoding="utf-8")
#: Pages a user reads as today's state (docs/history/ keeps what was true then).
PAGES = {
    p.relative_to(REPO).as_posix(): p.read_text(encoding="utf-8")
    for p in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    if "history" not in p.relative_to(REPO).parts
}
NUMBERS = "zero one two three four five six seven eight nine ten eleven twelve".split()


def test_the_version_is_written_once():
    import diacc

    assert diacc.__version__ == PYPROJECT["project"]["version"]


def test_every_torch_pin_is_the_one_ci_installs_and_the_package_accepts():
    ci = re.findall(r"torch==([\w.]+)", (REPO / ".ci" / "run").read_text(encoding="utf-8"))
    assert len(set(ci)) == 1
    pins = {(page, v) for page, text in PAGES.items() for v in re.findall(r"torch==([\w.]+)", text)}
    assert pins and {v for _, v in pins} == set(ci), sorted(pins)
    torch_spec = next(d for d in PYPROJECT["project"]["dependencies"] if d.startswith("torch"))
    assert ci[0] in SpecifierSet(torch_spec.removeprefix("torch"))


def test_the_python_version_is_pyprojects():
    minimum = PYPROJECT["project"]["requires-python"].removeprefix(">=")
    assert f"Python >= {minimum}" in README
    assert f"Python {minimum} or newer" in GETTING_STARTED


def test_the_number_of_tutorials_is_counted():
    count = len(list((REPO / "tutorials").glob("[0-9][0-9]_*.py")))
    claims = [
        (page, word)
        for page, text in PAGES.items()
        for word in re.findall(r"\b(\w+) scripts\b", text)
        if word in NUMBERS
    ]
    assert claims, "README and docs/index.md name the number of tutorial scripts"
    assert all(word == NUMBERS[count] for _, word in claims), (count, claims)


def test_every_shipped_checkpoint_is_listed_and_every_listed_one_ships():
    shipped = {p.name for p in (REPO / "checkpoints").glob("*.pt")}
    listed = set(
        re.findall(
            r"^\| `([^`]+\.pt)` \|",
            (REPO / "checkpoints" / "README.md").read_text(encoding="utf-8"),
            re.M,
        )
    )
    assert shipped and shipped == listed
    named = {n for text in PAGES.values() for n in re.findall(r"checkpoints/([\w.+-]+\.pt)", text)}
    assert named <= shipped, named - shipped


def test_no_page_types_a_count_of_tests():
    """The number of tests changes with every change: pages must not state it."""
    typed = [
        (page, m.group(0))
        for page, text in PAGES.items()
        for m in re.finditer(r"\b\d[\d,]* (?:tests|test cases)\b", text)
    ]
    assert not typed, typed


def _blocks(text: str) -> list[str]:
    return re.findall(r"^```bash\n(.*?)^```", text, re.S | re.M)


def test_getting_started_runs_readmes_commands():
    """README's quick start, training and test commands appear in Getting started verbatim."""
    readme = _blocks(README)
    assert len(readme) >= 3
    guide = "\n".join(_blocks(GETTING_STARTED))
    for block in readme:
        for line in block.splitlines():
            assert line in guide, f"README's {line!r} is not in docs/getting-started.md"

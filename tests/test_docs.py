"""The documentation site builds with no warning (``mkdocs build --strict``).

It generates the CLI reference from the parsers and the tutorial pages from
the scripts, and renders the API reference from the docstrings, so a renamed
option, tutorial or documented object breaks this test rather than the site.
"""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def test_docs_build_strict(tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (pip install -e '.[docs]')")
    pytest.importorskip(
        "mkdocstrings", reason="mkdocstrings is not installed (pip install -e '.[docs]')"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO), "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "WARNING" not in proc.stderr
    site = tmp_path / "site"
    cli = (site / "cli" / "index.html").read_text()
    assert "diacc plot timespace" in cli and "--view" in cli  # generated from the parsers
    for tutorial in sorted((REPO / "tutorials").glob("[0-9][0-9]_*.py")):
        page = (site / "tutorials" / tutorial.stem / "index.html").read_text()
        assert f'href="../{tutorial.stem}.ipynb"' in page  # the notebook to download
        _check_tutorial_outputs(page, site / "tutorials" / tutorial.stem, tutorial.stem)
        _check_notebook(site / "tutorials" / f"{tutorial.stem}.ipynb", tutorial)
    api = (site / "api" / "index.html").read_text()
    assert "load_policy" in api and "TrainedPolicy" in api
    assert not (site / "hooks.py").exists()
    assert (site / "history" / "learning-evidence" / "index.html").is_file()  # the dated record
    pages = [p.read_text() for p in site.rglob("*.html")]
    assert not any("facts.md" in page for page in pages)  # not in the repository


def _check_tutorial_outputs(page: str, page_dir: Path, stem: str) -> None:
    """The page shows the tutorial's cached outputs (docs/tutorials-output/): what it
    printed, and every figure it saved as an image that exists in the site."""
    cells = json.loads((REPO / "docs" / "tutorials-output" / stem / "outputs.json").read_text())
    printed = [line for cell in cells for line in cell["stdout"] if line.strip()]
    assert printed and printed[0] in html.unescape(page), stem
    figures = [figure for cell in cells for figure in cell["figures"]]
    images = re.findall(r'<img alt="[^"]*" src="([^"]+)"', page)
    assert [Path(src).name for src in images] == figures, stem
    for src in images:
        assert (page_dir / src).resolve().is_file(), f"{stem}: {src} is not in the site"


def _check_notebook(notebook: Path, script: Path) -> None:
    """A notebook Jupyter opens (nbformat 4, no jupytext) with the script's code, in order."""
    data = json.loads(notebook.read_text())
    assert data["nbformat"] == 4 and data["metadata"]["kernelspec"]["name"] == "python3"
    kinds = {cell["cell_type"] for cell in data["cells"]}
    assert kinds == {"markdown", "code"}, notebook
    code = ["".join(c["source"]) for c in data["cells"] if c["cell_type"] == "code"]
    text = script.read_text()
    position = 0
    for body in code:  # every code cell is a verbatim piece of the script, in order
        position = text.index(body, position) + len(body)
    compile("\n".join(code), str(notebook), "exec")
    assert "# %%" not in "".join(code)

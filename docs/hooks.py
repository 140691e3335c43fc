"""MkDocs hook: pages generated at build time, so they never drift from the code.

* ``cli.md``: every ``diacc`` command's ``--help``, from :func:`diacc.cli.build_parser`;
* ``tutorials/NN_name.md``: each jupytext tutorial script, its ``# %% [markdown]``
  cells as prose and its code cells as Python blocks, each followed by what it
  printed and the figures it saved. Those outputs are not computed here: they are
  cached in ``docs/tutorials-output/NN_name/`` by ``python docs/tutorial_outputs.py``,
  and ``tests/test_tutorials.py`` checks that the tutorials still print them. A
  missing or stale cache is a warning (so ``mkdocs build --strict`` fails);
* ``tutorials/NN_name.ipynb``: the same cells as a notebook to download, which
  Jupyter opens without jupytext (outputs empty: run it to see them).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from mkdocs.plugins import get_plugin_logger
from mkdocs.structure.files import File

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tutorial_outputs  # noqa: E402  (docs/tutorial_outputs.py)

REPO = Path(__file__).resolve().parent.parent
TUTORIALS = REPO / "tutorials"
log = get_plugin_logger("diacc-docs")


def _subcommands(parser: argparse.ArgumentParser, prefix: str):
    """(full command name, parser) of every command and nested subcommand, in order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                full = f"{prefix} {name}"
                yield full, sub
                yield from _subcommands(sub, full)


def cli_markdown() -> str:
    os.environ["COLUMNS"] = "90"  # argparse wraps help at the terminal width
    from diacc.cli import build_parser

    parser = build_parser()
    parts = [
        "# Command line reference",
        "",
        "Generated from the `diacc` command's own parsers when the site is built;",
        "`diacc COMMAND --help` prints the same text.",
        "",
        "```text",
        parser.format_help().rstrip(),
        "```",
    ]
    for name, sub in _subcommands(parser, "diacc"):
        parts += ["", f"## `{name}`", "", "```text", sub.format_help().rstrip(), "```"]
    return "\n".join(parts) + "\n"


def tutorial_cells(path: Path) -> list[tuple[str, str]]:
    """(``"markdown"`` or ``"code"``, text) of each cell of a jupytext percent script,
    the prose without its ``# `` prefixes; empty cells and the jupytext header left out."""
    return [(kind, body) for kind, body, _ in tutorial_outputs.tutorial_cells(path)]


def cached_outputs(path: Path) -> list[dict | None]:
    """Per code cell of the script, its cached outputs (``None`` where there are
    none or they are stale: each case logged as a warning)."""
    sources = tutorial_outputs.code_cells(path)
    cached = tutorial_outputs.load(path.stem)
    fix = f"run `{tutorial_outputs.REGENERATE}`"
    if cached is None:
        log.warning(f"tutorial {path.name} has no cached outputs: {fix}")
        return [None] * len(sources)
    if len(cached) != len(sources):
        log.warning(f"cached outputs of {path.name} are for another set of cells: {fix}")
        return [None] * len(sources)
    outputs: list[dict | None] = []
    for i, (source, cell) in enumerate(zip(sources, cached, strict=True)):
        fresh = cell["code"] == tutorial_outputs.code_hash(source)
        if not fresh:
            log.warning(f"{path.name}, code cell {i + 1}: its cached outputs are stale: {fix}")
        outputs.append(cell if fresh else None)
    return outputs


def tutorial_markdown(path: Path) -> str:
    """A jupytext percent script as Markdown: prose cells unwrapped, code cells fenced."""
    out = [
        f"*Source: `tutorials/{path.name}` (run it with `python tutorials/{path.name}`; "
        "the test suite runs it too). As a notebook for Jupyter: "
        f"[{path.stem}.ipynb]({path.stem}.ipynb). Under each piece of code: what it "
        "printed and the figures it saved, when the tutorial last ran with the "
        "small budgets of the test suite.*",
        "",
    ]
    outputs = iter(cached_outputs(path))
    for kind, body in tutorial_cells(path):
        if kind == "markdown":
            out += [body, ""]
            continue
        out += ["```python", body, "```", ""]
        cell = next(outputs)
        if cell is None:
            continue
        if cell["stdout"]:
            out += ["```text", *cell["stdout"], "```", ""]
        for figure in cell["figures"]:
            out += [f"![{figure}](../{tutorial_outputs.CACHE.name}/{path.stem}/{figure})", ""]
    return "\n".join(out)


def tutorial_notebook(path: Path) -> str:
    """The script's cells as an nbformat 4 notebook (JSON), outputs empty."""

    def cell(kind: str, body: str) -> dict:
        source = body.splitlines(keepends=True)
        if kind == "markdown":
            return {"cell_type": "markdown", "metadata": {}, "source": source}
        return {
            "cell_type": "code",
            "execution_count": None,
            "metadata": {},
            "outputs": [],
            "source": source,
        }

    notebook = {
        "cells": [cell(kind, body) for kind, body in tutorial_cells(path)],
        "metadata": {
            "kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
            "language_info": {"name": "python"},
        },
        "nbformat": 4,
        "nbformat_minor": 4,
    }
    return json.dumps(notebook, indent=1) + "\n"


def on_files(files, config):
    files.append(File.generated(config, "cli.md", content=cli_markdown()))
    for path in sorted(TUTORIALS.glob("[0-9][0-9]_*.py")):
        files.append(
            File.generated(config, f"tutorials/{path.stem}.md", content=tutorial_markdown(path))
        )
        files.append(
            File.generated(config, f"tutorials/{path.stem}.ipynb", content=tutorial_notebook(path))
        )
    return files

"""MkDocs hook: pages generated at build time, so they never drift from the code.

* ``cli.md``: every ``diacc`` command's ``--help``, from :func:`diacc.cli.build_parser`;
* ``tutorials/NN_name.md``: each jupytext tutorial script, its ``# %% [markdown]``
  cells as prose and its code cells as Python blocks (not executed here:
  ``tests/test_tutorials.py`` runs them);
* ``tutorials/NN_name.ipynb``: the same cells as a notebook to download, which
  Jupyter opens without jupytext (outputs empty: run it to see them).
"""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path

from mkdocs.structure.files import File

REPO = Path(__file__).resolve().parent.parent
TUTORIALS = REPO / "tutorials"


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
    text = path.read_text()
    text = re.sub(r"\A# ---\n(?:#.*\n)*?# ---\n", "", text)  # the jupytext header
    parts = re.split(r"^# %%(.*)$", text, flags=re.M)
    cells = []
    for marker, body in zip(parts[1::2], parts[2::2], strict=True):
        body = body.strip("\n")
        if not body.strip():
            continue
        if "[markdown]" in marker:
            prose = [re.sub(r"^# ?", "", line) for line in body.splitlines()]
            cells.append(("markdown", "\n".join(prose)))
        else:
            cells.append(("code", body))
    return cells


def tutorial_markdown(path: Path) -> str:
    """A jupytext percent script as Markdown: prose cells unwrapped, code cells fenced."""
    out = [
        f"*Source: `tutorials/{path.name}` (run it with `python tutorials/{path.name}`; "
        "the test suite runs it too). As a notebook for Jupyter: "
        f"[{path.stem}.ipynb]({path.stem}.ipynb).*",
        "",
    ]
    for kind, body in tutorial_cells(path):
        out += [body] if kind == "markdown" else ["```python", body, "```"]
        out.append("")
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

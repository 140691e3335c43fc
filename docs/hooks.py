"""MkDocs hook: pages generated at build time, so they never drift from the code.

* ``cli.md``: every ``diacc`` command's ``--help``, from :func:`diacc.cli.build_parser`;
* ``tutorials/NN_name.md``: each jupytext tutorial script, its ``# %% [markdown]``
  cells as prose and its code cells as Python blocks (not executed here:
  ``tests/test_tutorials.py`` runs them).
"""

from __future__ import annotations

import argparse
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


def tutorial_markdown(path: Path) -> str:
    """A jupytext percent script as Markdown: prose cells unwrapped, code cells fenced."""
    text = path.read_text()
    text = re.sub(r"\A# ---\n(?:#.*\n)*?# ---\n", "", text)  # the jupytext header
    cells = re.split(r"^# %%(.*)$", text, flags=re.M)
    out = [
        f"*Source: `tutorials/{path.name}` (run it with `python tutorials/{path.name}`; "
        "the test suite runs it too).*",
        "",
    ]
    for marker, body in zip(cells[1::2], cells[2::2], strict=True):
        body = body.strip("\n")
        if not body.strip():
            continue
        if "[markdown]" in marker:
            out.append("\n".join(re.sub(r"^# ?", "", line) for line in body.splitlines()))
        else:
            out += ["```python", body, "```"]
        out.append("")
    return "\n".join(out)


def on_files(files, config):
    files.append(File.generated(config, "cli.md", content=cli_markdown()))
    for path in sorted(TUTORIALS.glob("[0-9][0-9]_*.py")):
        files.append(
            File.generated(config, f"tutorials/{path.stem}.md", content=tutorial_markdown(path))
        )
    return files

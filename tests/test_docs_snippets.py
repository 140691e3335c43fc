"""Docs that cannot drift (issue 42): the code in README and docs/ runs as written.

* Every ```` ```python ```` block runs as a script in a temporary directory
  outside the repository (a user's working directory), with the package as
  installed. A block that needs a long run carries a line
  ``# docs-test: skip (why)``; this test honours it and needs the reason.
* Every ``diacc ...`` command of a ```` ```bash ```` block is parsed by the real
  ``diacc`` parser (nothing runs), and every ``python FILE`` / ``bash FILE``
  of one names a file that exists, so a renamed option, subcommand or moved
  script fails here. README's quick start also runs, at 1 episode of 10 steps.

Inline code in prose (``diacc eval --backend B``) is usage notation with
placeholders and is not parsed; ``docs/history/`` is exempt: it records
commands as they were run.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
#: The pages whose code a user copies.
PAGES = sorted(
    [REPO / "README.md", *(REPO / "docs").rglob("*.md")],
    key=lambda p: str(p),
)
PAGES = [p for p in PAGES if "history" not in p.relative_to(REPO).parts]
SKIP = re.compile(r"#\s*docs-test:\s*skip\s*\((.+)\)")
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def blocks(language: set[str]) -> list[tuple[str, str]]:
    """(page:line, code) of every fenced block in one of ``language`` on the pages."""
    found = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for m in FENCE.finditer(text):
            if m.group(1) in language:
                line = text[: m.start()].count("\n") + 1
                found.append((f"{page.relative_to(REPO)}:{line}", m.group(2)))
    return found


PYTHON = blocks({"python"})
SHELL = blocks({"bash", "sh", "shell", "console"})


def test_the_pages_have_code_to_check():
    assert len(PYTHON) >= 3 and len(SHELL) >= 10  # the extraction still finds the blocks


@pytest.mark.parametrize("where, code", PYTHON, ids=[w for w, _ in PYTHON])
def test_python_snippet_runs_outside_the_repository(where, code, tmp_path):
    skip = SKIP.search(code)
    if skip:
        pytest.skip(f"{where}: {skip.group(1)}")
    script = tmp_path / "snippet.py"
    script.write_text(code, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"{where}:\n{proc.stderr[-3000:]}"
    assert "Traceback" not in proc.stderr, f"{where}:\n{proc.stderr[-3000:]}"


def expand_braces(word: str) -> list[str]:
    """Bash's ``a{b,c}d`` -> ``abd acd`` (one level, as the docs write it)."""
    m = re.search(r"\{([^{}]*,[^{}]*)\}", word)
    if not m:
        return [word]
    return [word[: m.start()] + alt + word[m.end() :] for alt in m.group(1).split(",")]


def commands(code: str) -> list[list[str]]:
    """The simple commands of a shell block: continuation lines joined, comments dropped,
    ``$(...)`` replaced by one word, split at ``&&``, ``||``, ``;`` and ``|``; ``for ...
    do``, ``done`` and leading ``VAR=value`` assignments removed (a loop variable takes
    its first value); braces expanded and an optional part written ``[--option value]``
    taken as given."""
    out, loop = [], {}
    for line in code.replace("\\\n", " ").splitlines():
        line = re.sub(r"(^|\s)#.*$", "", line).strip()
        line = re.sub(r"\$\([^)]*\)", "SUBST", line).replace("[", "").replace("]", "")
        if line.startswith("$ "):
            line = line[2:]
        for part in re.split(r"&&|\|\||;|\|", line):
            words = shlex.split(part, posix=True) if part.strip() else []
            words = [w for word in words for w in expand_braces(word)]
            if words[:1] == ["do"]:
                words = words[1:]
            if words[:1] == ["for"] and len(words) > 3 and words[2] == "in":
                loop[words[1]] = words[3]
                continue
            if words[:1] == ["done"]:
                continue
            for name, value in loop.items():
                words = [re.sub(rf"\$\{{?{name}\}}?(?!\w)", value, w) for w in words]
            while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):
                words = words[1:]
            if words and words[0] in {"nice", "time"}:
                words = words[1:] if words[0] == "time" else words[3:]
            if words:
                out.append(words)
    return out


SHELL_COMMANDS = [(where, words) for where, code in SHELL for words in commands(code)]
DIACC_COMMANDS = [(w, c) for w, c in SHELL_COMMANDS if c[0] == "diacc"]
SCRIPTS = [
    (w, c[1])
    for w, c in SHELL_COMMANDS
    if c[0] in {"python", "bash"} and len(c) > 1 and c[1].endswith((".py", ".sh"))
]


def test_every_diacc_command_in_the_docs_parses(monkeypatch):
    from diacc.cli import build_parser

    monkeypatch.chdir(REPO)  # the commands are written for the clone's root
    assert len(DIACC_COMMANDS) >= 10
    bad = []
    for where, words in DIACC_COMMANDS:
        if "--help" in words or "-h" in words or "--version" in words:
            continue
        try:
            build_parser().parse_args(words[1:])
        except SystemExit as exc:
            if exc.code:
                bad.append(f"{where}: {shlex.join(words)}")
    assert not bad, "commands the parser refuses:\n" + "\n".join(bad)


def test_every_script_the_docs_run_exists():
    assert SCRIPTS
    missing = [f"{w}: {s}" for w, s in SCRIPTS if not (REPO / s).is_file()]
    assert not missing, "scripts that do not exist:\n" + "\n".join(missing)


def test_readmes_quick_start_runs_at_a_tiny_budget(tmp_path):
    """README's quick start as written, from the clone's root, with 1 episode of 10 steps
    instead of 3 of 330 and its output in a temporary directory (the install left out)."""
    block = next(code for where, code in SHELL if where.startswith("README") and "eval" in code)
    assert "--episodes 3" in block and "--episode-steps 330" in block
    steps = [s for s in block.strip().split(" && ") if not s.startswith("pip ")]
    tiny = (
        " && ".join(steps)
        .replace("--episodes 3", "--episodes 1")
        .replace("--episode-steps 330", "--episode-steps 10")
        .replace("results/quickstart", str(tmp_path / "quickstart"))
    )
    diacc = f'diacc() {{ "{sys.executable}" -m diacc.cli "$@"; }}; '  # this tree's diacc
    proc = subprocess.run(
        ["bash", "-c", diacc + tiny],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| same-mix | heuristic | diacc |" in proc.stdout
    assert "| Delay (s/veh) |" in proc.stdout


#: A path into the tree as the pages name them (in code, links or prose).
TREE_PATH = re.compile(
    r"(?<![\w/.$-])(?:--out )?((?:benchmarks|checkpoints|configs|maps|tutorials|examples|tests"
    r"|docs|diacc)/[\w.*+,/-]*[\w*])"
)


def test_every_path_the_pages_name_exists():
    """A moved or renamed file breaks this test, not a reader's copy-paste. Outputs
    (``--out PATH``) are not inputs; a tutorial page is generated from its script; the
    rename map of benchmarks/README.md names old paths on purpose."""
    readmes = [p for p in (REPO / "benchmarks").rglob("README.md") if "results" not in p.parts]
    pages = [*PAGES, REPO / "checkpoints" / "README.md", *readmes]
    missing = []
    for page in pages:
        text = page.read_text(encoding="utf-8").split("## Rename map")[0]
        for m in TREE_PATH.finditer(text):
            path = m.group(1)
            if m.group(0).startswith("--out "):
                continue
            paths = [path]
            if path.startswith("tutorials/") and path.endswith(".md"):
                paths.append(path[:-3] + ".py")
            if any(next(b.glob(p), None) for b in (REPO, page.parent) for p in paths):
                continue
            if path.startswith("docs/img/") and next(REPO.glob(path + ".*"), None):
                continue  # a figure's prefix, as `diacc plot --out` takes it
            missing.append(f"{page.relative_to(REPO)}: {path}")
    assert not missing, "paths that do not exist:\n" + "\n".join(missing)

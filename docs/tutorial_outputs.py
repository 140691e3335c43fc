"""The tutorials' printed output and figures, cached for their docs pages.

Regenerate every tutorial's cached output (about as long as
``pytest tests/test_tutorials.py``) with::

    python docs/tutorial_outputs.py

It runs each ``tutorials/NN_name.py`` in order, in its own Python process, cell
by cell (``# %%`` cells, as Jupyter would), with ``MPLBACKEND=Agg`` and
``DIACC_TUTORIAL_OUT`` set to a temporary folder that all tutorials share (as
``tests/test_tutorials.py`` does: that test runs them through :func:`run_cells`
too and fails when what they print no longer matches the cache). It writes,
per tutorial, ``docs/tutorials-output/NN_name/``:

* ``outputs.json``: per code cell, a hash of its code, the lines it printed to stdout
  (the temporary folder written as ``tutorial_out``, the tutorials' default
  folder) and the PNG figures it wrote;
* those PNG figures, downscaled where a file exceeds :data:`MAX_PNG_BYTES`.

``docs/hooks.py`` puts each cell's printed text and figures under its code on
the tutorial's page. This file imports nothing from ``diacc``: the tutorials
do, in the child processes.
"""

from __future__ import annotations

import builtins
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TUTORIALS = REPO / "tutorials"
CACHE = REPO / "docs" / "tutorials-output"
REGENERATE = "python docs/tutorial_outputs.py"
#: A cached PNG larger than this is downscaled (keeps the repository small).
MAX_PNG_BYTES = 150_000
#: How a printed path to the temporary output folder is written in the cache.
OUT_PLACEHOLDER = "tutorial_out"
#: Line the child process prints after each code cell, then a JSON object.
_MARK = "@@diacc-tutorial-cell@@ "


def tutorial_cells(path: Path) -> list[tuple[str, str, int]]:
    """(``"markdown"`` or ``"code"``, text, first line number) of each cell of a
    jupytext percent script, the prose without its ``# `` prefixes; empty cells
    and the jupytext header left out."""
    text = path.read_text()
    header = re.match(r"\A# ---\n(?:#.*\n)*?# ---\n", text)
    offset = header.end() if header else 0
    parts = re.split(r"^# %%(.*)$", text[offset:], flags=re.M)
    if parts[0].strip():
        raise ValueError(f"{path.name}: code before the first '# %%' cell")
    line = text[:offset].count("\n") + 1 + parts[0].count("\n")
    cells = []
    for marker, body in zip(parts[1::2], parts[2::2], strict=True):
        start = line + 1  # the line after the '# %%' marker (on line `line`)
        line += body.count("\n")  # body runs from the marker's newline to the next marker
        stripped = body.lstrip("\n")
        first = start + len(body) - len(stripped) - 1  # body starts with the marker's newline
        body = stripped.rstrip("\n")
        if not body.strip():
            continue
        if "[markdown]" in marker:
            prose = [re.sub(r"^# ?", "", row) for row in body.splitlines()]
            cells.append(("markdown", "\n".join(prose), first))
        else:
            cells.append(("code", body, first))
    return cells


def code_cells(path: Path) -> list[str]:
    return [body for kind, body, _ in tutorial_cells(path) if kind == "code"]


def code_hash(source: str) -> str:
    """Short hash of a code cell: tells a cached output from one of older code."""
    return hashlib.sha256(source.encode()).hexdigest()[:12]


@dataclass
class CellOutput:
    source: str
    stdout: list[str] = field(default_factory=list)
    #: PNG files the cell wrote, relative to ``DIACC_TUTORIAL_OUT``.
    figures: list[str] = field(default_factory=list)


@dataclass
class TutorialRun:
    name: str
    out_dir: Path
    cells: list[CellOutput]
    stdout: str  # everything printed, as the plain script prints it
    stderr: str


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {
        p.relative_to(root).as_posix(): (p.stat().st_mtime_ns, p.stat().st_size)
        for p in root.rglob("*.png")
        if p.is_file()
    }


def _exec_cells(script: Path) -> None:
    """Child process: run the script's code cells in one namespace, as ``python
    script`` would (``__name__``, ``__file__``, ``sys.argv``, ``sys.path[0]``),
    printing a marker and the PNGs each cell wrote after it."""
    out_root = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out"))
    sys.argv = [str(script)]
    sys.path[0] = str(script.parent)
    namespace = {"__name__": "__main__", "__file__": str(script), "__builtins__": builtins}
    for kind, body, first in tutorial_cells(script):
        if kind != "code":
            continue
        before = _snapshot(out_root) if out_root.is_dir() else {}
        code = compile("\n" * (first - 1) + body, str(script), "exec")  # tracebacks: real lines
        exec(code, namespace)
        after = _snapshot(out_root) if out_root.is_dir() else {}
        written = sorted(rel for rel, stamp in after.items() if before.get(rel) != stamp)
        sys.stdout.flush()
        sys.stderr.flush()
        print(_MARK + json.dumps({"figures": written}), flush=True)


def run_cells(name: str, out_dir: Path, timeout: float = 600) -> TutorialRun:
    """Run ``tutorials/<name>`` cell by cell in a child process (cwd and
    ``DIACC_TUTORIAL_OUT`` = *out_dir*, ``MPLBACKEND=Agg``, the default training
    budget); raises if it fails."""
    script = TUTORIALS / name
    env = {**os.environ, "DIACC_TUTORIAL_OUT": str(out_dir), "MPLBACKEND": "Agg"}
    env["PYTHONUNBUFFERED"] = "1"  # keeps prints and cell markers in order
    env.pop("DIACC_TUTORIAL_TRAIN_STEPS", None)  # the cache shows the default budget
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--exec-cells", str(script)],
        cwd=out_dir,  # a tutorial that ignored DIACC_TUTORIAL_OUT would still stay out of the repo
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{name} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    sources = code_cells(script)
    cells, lines, plain = [], [], []
    for row in proc.stdout.splitlines():
        if row.startswith(_MARK):
            figures = json.loads(row[len(_MARK) :])["figures"]
            cells.append(CellOutput(sources[len(cells)], lines, figures))
            lines = []
        else:
            lines.append(row)
            plain.append(row)
    assert len(cells) == len(sources) and not lines, f"{name}: output after the last cell"
    return TutorialRun(name, out_dir, cells, "\n".join(plain) + "\n", proc.stderr)


def normalise(lines: list[str], out_dir: Path) -> list[str]:
    """Printed lines as cached: the temporary output folder written as ``tutorial_out``
    (where the tutorials write by default), trailing spaces dropped."""
    out = str(out_dir)
    return [line.replace(out, OUT_PLACEHOLDER).rstrip() for line in lines]


def cached_name(figure: str, tutorial: str) -> str:
    """File name in the cache of a figure at *figure* (relative to the output root)."""
    prefix = f"{tutorial}/"
    rel = figure[len(prefix) :] if figure.startswith(prefix) else figure
    return rel.replace("/", "-")


def record(run: TutorialRun) -> list[dict]:
    """The cache's ``outputs.json`` content for one run."""
    stem = Path(run.name).stem
    return [
        {
            "code": code_hash(cell.source),
            "stdout": normalise(cell.stdout, run.out_dir),
            "figures": [cached_name(f, stem) for f in cell.figures],
        }
        for cell in run.cells
    ]


def load(stem: str) -> list[dict] | None:
    path = CACHE / stem / "outputs.json"
    return json.loads(path.read_text()) if path.is_file() else None


def differences(run: TutorialRun) -> list[str]:
    """How *run* differs from the cache (empty when it matches): cells' code exactly,
    printed text with every number masked (:func:`_masked`: training and float
    printing may differ in the last digits on another CPU, so CI checks the text
    around the numbers), figures by name; the PNGs' pixels are not compared (the run
    must have written them, and the cached files must exist)."""
    stem = Path(run.name).stem
    cached = load(stem)
    if cached is None:
        return [f"{stem}: no cached outputs in {CACHE.relative_to(REPO)}/{stem}/"]
    now = record(run)
    problems = []
    if len(cached) != len(now):
        problems.append(f"{stem}: {len(now)} code cells, the cache has {len(cached)}")
    for i, (old, new) in enumerate(zip(cached, now, strict=False)):
        where = f"{stem}, code cell {i + 1}"
        if old["code"] != new["code"]:
            problems.append(f"{where}: its code changed since the cache was written")
        if _masked(old["stdout"]) != _masked(new["stdout"]):
            diff = _first_difference(_masked(old["stdout"]), _masked(new["stdout"]))
            problems.append(f"{where}: prints something else now; {diff}")
        if old["figures"] != new["figures"]:
            problems.append(f"{where}: wrote figures {new['figures']}, cached {old['figures']}")
        for figure in old["figures"]:
            if not (CACHE / stem / figure).is_file():
                problems.append(f"{where}: cached figure {figure} is missing")
    return problems


_NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _masked(lines: list[str]) -> list[str]:
    """Printed lines with every number replaced by ``#``."""
    return [_NUMBER.sub("#", line) for line in lines]


def _first_difference(old: list[str], new: list[str]) -> str:
    for j, (a, b) in enumerate(zip(old, new, strict=False)):
        if a != b:
            return f"line {j + 1}: cached {a!r}, now {b!r}"
    return f"cached {len(old)} lines, now {len(new)}"


def _write_png(source: Path, target: Path) -> None:
    """Copy a PNG, downscaled (and palette-quantised) when larger than MAX_PNG_BYTES."""
    shutil.copyfile(source, target)
    if target.stat().st_size <= MAX_PNG_BYTES:
        return
    from PIL import Image  # matplotlib's dependency

    with Image.open(source) as original:
        image = original.convert("RGB")
    scale = 1.0
    while target.stat().st_size > MAX_PNG_BYTES and scale > 0.3:
        size = (round(image.width * scale), round(image.height * scale))
        small = image.resize(size, Image.Resampling.LANCZOS) if scale < 1 else image
        small.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(target, optimize=True)
        scale *= 0.85


def write_cache(run: TutorialRun) -> None:
    stem = Path(run.name).stem
    folder = CACHE / stem
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for cell in run.cells:
        for figure in cell.figures:
            _write_png(run.out_dir / figure, folder / cached_name(figure, stem))
    text = json.dumps(record(run), indent=1, ensure_ascii=False)
    (folder / "outputs.json").write_text(text + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--exec-cells"]:
        _exec_cells(Path(argv[1]))
        return 0
    if argv:
        print(__doc__)
        return 2
    names = sorted(p.name for p in TUTORIALS.glob("[0-9][0-9]_*.py"))
    for folder in CACHE.glob("*/"):  # a renamed or removed tutorial's outputs
        if f"{folder.name}.py" not in names:
            shutil.rmtree(folder)
    with tempfile.TemporaryDirectory(prefix="diacc-tutorials-") as tmp:
        for name in names:  # in order, in one folder: tutorial 7 reuses tutorial 6's agent
            print(f"running {name} ...", flush=True)
            run = run_cells(name, Path(tmp))
            write_cache(run)
            folder = CACHE / Path(name).stem
            sizes = ", ".join(
                f"{p.name} {p.stat().st_size // 1000} kB" for p in sorted(folder.glob("*.png"))
            )
            print(f"  wrote {folder.relative_to(REPO)}/: outputs.json, {sizes or 'no figures'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Package structure (issue 24): one error base, no import circles, layers that import
downwards only.

Every exception class diacc defines is a :class:`~diacc.errors.DiaccError`
(keeping its builtin base), so the command line prints it as one line; only
the ``KeyboardInterrupt`` subclasses that carry a signal stay outside it.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path

import diacc
from diacc.errors import DiaccError


def _modules() -> list[str]:
    return sorted(m.name for m in pkgutil.walk_packages(diacc.__path__, "diacc."))


def test_every_error_class_is_a_diacc_error_and_keeps_its_builtin_base():
    outside, checked = [], 0
    for name in _modules():
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if not (inspect.isclass(obj) and issubclass(obj, BaseException)):
                continue
            if obj.__module__ != name or not issubclass(obj, Exception):
                continue  # BaseExceptions are control flow (a time limit), never reported
            checked += 1
            if not issubclass(obj, DiaccError):
                outside.append(f"{name}.{obj.__name__}")
            elif obj is not DiaccError:
                assert issubclass(obj, (ValueError, RuntimeError)), obj
    assert checked >= 20 and outside == []


def _import_graph() -> dict[str, set[str]]:
    """diacc module -> the diacc modules it imports, read from the source: every import
    statement counts, those inside functions and under ``TYPE_CHECKING`` too."""
    root = Path(diacc.__file__).parent
    files = {}
    for path in root.rglob("*.py"):
        parts = ("diacc", *path.relative_to(root).with_suffix("").parts)
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path

    def owner(name: str) -> str:  # the module a dotted name lives in
        while name not in files:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                imported |= {f"{node.module}.{a.name}" for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                raise AssertionError(f"{path}: relative import")
        graph[module] = {
            owner(name) for name in imported if name.startswith("diacc.") or name == "diacc"
        } - {module, "diacc"}
    return graph


def test_no_import_circles():
    """A module never imports, even lazily, a module that imports it back (issue 24:
    mappo <-> checkpoint, backends.base -> its implementations)."""
    graph = _import_graph()
    assert {"diacc.learn.mappo", "diacc.sim.backends.base"} <= set(graph)
    done: set[str] = set()

    def walk(module: str, path: list[str]) -> None:
        if module in path:
            raise AssertionError("import circle: " + " -> ".join(path[path.index(module) :]))
        if module in done:
            return
        for child in sorted(graph[module]):
            walk(child, [*path, module])
        done.add(module)

    for module in sorted(graph):
        walk(module, [])


#: The layer packages in data-flow order, lowest first: a module imports modules of its
#: own layer and of those below, never of one above (even lazily).
LAYERS = ("diacc.sim", "diacc.envs", "diacc.learn", "diacc.experiments", "diacc.cli")
#: The top-level modules, each with the highest layer it may import (None: none).
SHARED = {
    "diacc.errors": None,
    "diacc.tomlfile": None,
    "diacc.fileio": None,
    "diacc.runlog": None,
    "diacc.threads": None,
    "diacc.fields": None,  # checked settings: every config section, the simulator's too
    "diacc.records": None,  # batched records: row operations by declared axes (issue 59)
    "diacc.config": "diacc.sim",  # the config tree nests the simulator's sections
    "diacc.config.env": "diacc.sim",
    "diacc.config.train": "diacc.sim",
    "diacc.config.mix": "diacc.sim",
    "diacc.config.overrides": "diacc.sim",
    "diacc.config.stored": "diacc.sim",
    "diacc.config.checks": "diacc.sim",
    "diacc.shipped": None,  # where the installed package keeps its maps and checkpoints
    "diacc.__main__": "diacc.cli",  # python -m diacc
    "diacc.console": "diacc.envs",  # prints EpisodeMetrics (learn and experiments use it)
    "diacc": "diacc.experiments",  # parallel_env, env, load_policy: lazy, on call
}


def _rank(module: str) -> int:
    """Index of the module's layer in LAYERS; -1 for a top-level module."""
    return next((i for i, p in enumerate(LAYERS) if f"{module}.".startswith(f"{p}.")), -1)


def _upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """``"X imports Y"`` for every import of a layer above the importer's (above the
    ceiling SHARED gives a top-level module)."""
    upward = []
    for module, imported in sorted(graph.items()):
        ceiling = _rank(module)
        if ceiling < 0:
            ceiling = -1 if SHARED[module] is None else LAYERS.index(SHARED[module])
        upward += [f"{module} imports {n}" for n in sorted(imported) if _rank(n) > ceiling]
    return upward


def test_layers_import_downwards():
    """sim never imports envs, learn, experiments or cli; envs never learn, experiments
    or cli; learn never experiments or cli; experiments never cli. A new top-level
    module has to go into a layer or be listed in SHARED with its ceiling."""
    graph = _import_graph()
    assert {m for m in graph if _rank(m) < 0} == set(SHARED)
    # the simulator's settings live in diacc.sim: the config imports sim, never back
    assert [
        f"{m} imports {n}"
        for m, imported in sorted(graph.items())
        if _rank(m) == 0
        for n in sorted(imported)
        if n == "diacc.config" or n.startswith("diacc.config.")
    ] == []
    assert {LAYERS[_rank(m)] for m in graph if _rank(m) >= 0} == set(LAYERS)
    assert _upward_imports(graph) == []
    # the check sees a lazy upward import (as the AST finds it)
    assert _upward_imports({"diacc.sim.maps": {"diacc.envs.env"}}) == [
        "diacc.sim.maps imports diacc.envs.env"
    ]

"""Where the shipped maps and trained agents are, in any installation.

They are package data (``diacc/data/maps/*.toml``, ``diacc/data/checkpoints/*.pt``)
found through :mod:`importlib.resources`, so a wheel or sdist installed anywhere, an
editable install and a clone on ``PYTHONPATH`` all find them the same way; a path
computed from the repository's layout (as before) exists only in a clone.

In the repository, ``diacc/data/maps`` and ``diacc/data/checkpoints`` are symbolic
links to the top-level ``maps/`` and ``checkpoints/`` that contributors edit (one
copy of each file); building an sdist or a wheel copies the files they point to
(``[tool.setuptools.package-data]`` in ``pyproject.toml``), which CI checks by
installing the wheel outside the clone (``.ci/wheel_smoke.sh``).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from diacc.errors import DiaccError

#: File name suffix of a checkpoint.
CHECKPOINT_SUFFIX = ".pt"


class ShippedDataError(DiaccError, RuntimeError):
    """The installation lacks its shipped maps or checkpoints; the message is one line."""


def data_dir(kind: str) -> Path:
    """The folder of shipped ``kind`` (``"maps"`` or ``"checkpoints"``) as a file-system path.

    A path, not an :class:`importlib.resources.abc.Traversable`: maps are read and
    checkpoints loaded by ``torch.load`` from files. Every installer unpacks diacc's
    wheel into files, so this holds; a zip-imported diacc gets a one-line error.
    """
    resource = files("diacc").joinpath("data", kind)
    if not isinstance(resource, Path):
        raise ShippedDataError(
            f"shipped {kind} of diacc are not files on disk ({resource}); "
            "install diacc with pip (a wheel unpacks them)"
        )
    return resource


def require_dir(kind: str) -> Path:
    """:func:`data_dir`, checked to be a folder: a clone whose symbolic links were checked
    out as text files (git on Windows without ``core.symlinks``) gets a one-line error."""
    folder = data_dir(kind)
    if not folder.is_dir():
        raise ShippedDataError(
            f"the shipped {kind} folder {folder} is missing or not a folder (in a clone it is "
            f"a symbolic link to ../../{kind}: clone with symbolic links enabled)"
        )
    return folder


def shipped_checkpoints() -> list[str]:
    """File names of the shipped trained agents, sorted."""
    return sorted(p.name for p in require_dir("checkpoints").glob(f"*{CHECKPOINT_SUFFIX}"))


def shipped_checkpoint(name: str) -> Path | None:
    """The shipped checkpoint called ``name`` (file name, with or without ``.pt``), or None.

    Lets ``diacc eval --policy NAME`` and :func:`diacc.load_policy` name a shipped agent
    from any working directory; anything with a folder part is a path, not a name.
    """
    if Path(name).name != name or not name:
        return None
    file_name = name if name.endswith(CHECKPOINT_SUFFIX) else name + CHECKPOINT_SUFFIX
    return require_dir("checkpoints") / file_name if file_name in shipped_checkpoints() else None

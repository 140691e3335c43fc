"""Package structure (issue 24): one error base, no import circles.

Every exception class diacc defines is a :class:`~diacc.errors.DiaccError`
(keeping its builtin base), so the command line prints it as one line; only
the ``KeyboardInterrupt`` subclasses that carry a signal stay outside it.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

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
            if obj.__module__ != name or issubclass(obj, KeyboardInterrupt):
                continue
            checked += 1
            if not issubclass(obj, DiaccError):
                outside.append(f"{name}.{obj.__name__}")
            elif obj is not DiaccError:
                assert issubclass(obj, (ValueError, RuntimeError)), obj
    assert checked >= 20 and outside == []

"""Config axes of ``diacc sweep`` and ``diacc reproduce``: ``--sweep KEY=V1,V2,...``.

A sweep over config values trains one run per *setting* (a point of the
product of the axes) and keeps the settings apart everywhere: in run names
and directories, in the finished-run check and in the training curves. An
axis is one dotted config key with its values, or several keys whose values
move together (``KEY1,KEY2=A1:B1,A2:B2``), for settings the paper varies as
a pair:

* the **tau study** (paper Fig. "training curves" (d)-(f)) compares the
  annealed temperature 2 -> 0.05 against fixed tau = 0.05, 2 and 10; a fixed
  tau is ``tau_init = tau_final``;
* the **w_e study** ((g)-(i)) varies the ego weight with w_g = 1 - w_e (see
  :class:`diacc.config.RewardConfig`).

:data:`STUDIES` holds both as ready axes (``--study tau``, ``--study w_e``).
Every value is parsed by the config's own override (the field's type) and
checked by :func:`diacc.config.validate` before anything is written; bad input
raises :class:`diacc.config.ConfigError` with a one-line message.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from typing import Any

from diacc.config import ConfigError, TrainConfig, override, validate

#: Keys a sweep varies with its own options (``--variants``, ``--maps``, ``--seeds``).
OWN_AXES = {"variant": "--variants", "env.map": "--maps", "seed": "--seeds", "run_dir": "--out"}
#: The paper's two selection studies as sweep axes (module docstring). The paper
#: names w_e = 0 to 0.4, 0.6, 0.8 and 1.0; 0.2 is our step inside "0 to 0.4".
STUDIES: dict[str, str] = {
    "tau": "env.reward.tau_init,env.reward.tau_final=2:0.05,0.05:0.05,2:2,10:10",
    "w_e": "env.reward.w_ego,env.reward.w_global=0:1,0.2:0.8,0.4:0.6,0.6:0.4,0.8:0.2,1:0",
}


@dataclass(frozen=True)
class Axis:
    """One ``--sweep`` option: keys that move together and one value tuple per point."""

    keys: tuple[str, ...]
    points: tuple[tuple[str, ...], ...]  # as typed; each as long as ``keys``


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: the config values that differ between its runs."""

    values: tuple[tuple[str, Any], ...] = ()  # (dotted key, value of the field's type)

    @property
    def changes(self) -> dict[str, Any]:
        return dict(self.values)

    @property
    def name(self) -> str:
        """File-name part, e.g. ``tau_init2-tau_final0.05`` ("" for no setting)."""
        short = short_keys([k for k, _ in self.values])
        parts = [f"{short[k]}{format_value(v)}" for k, v in self.values]
        return re.sub(r"[^A-Za-z0-9._-]", "_", "-".join(parts))

    @property
    def label(self) -> str:
        """Legend text, e.g. ``tau_init=2, tau_final=0.05`` ("" for no setting)."""
        short = short_keys([k for k, _ in self.values])
        return ", ".join(f"{short[k]}={format_value(v)}" for k, v in self.values)


def format_value(value: Any) -> str:
    """A config value as run names and legends show it (floats without trailing zeros)."""
    return f"{value:g}" if isinstance(value, float) else str(value)


def short_keys(keys: list[str]) -> dict[str, str]:
    """Each key's last part, or the whole key where two keys share a last part."""
    leaves = [k.rsplit(".", 1)[-1] for k in keys]
    return {k: leaf if leaves.count(leaf) == 1 else k for k, leaf in zip(keys, leaves, strict=True)}


def parse_axis(text: str) -> Axis:
    """``KEY=V1,V2`` or ``KEY1,KEY2=A1:B1,A2:B2`` -> :class:`Axis` (syntax only)."""
    if "=" not in text:
        raise ConfigError(f"--sweep expects KEY=V1,V2,... got {text!r}")
    head, tail = text.split("=", 1)
    keys = tuple(k.strip() for k in head.split(","))
    if not all(keys):
        raise ConfigError(f"--sweep {text!r}: a key is empty")
    if len(set(keys)) < len(keys):
        raise ConfigError(f"--sweep {text!r} names a key twice")
    items = [v.strip() for v in tail.split(",")]
    if not any(items):
        raise ConfigError(f"--sweep {text!r}: the value list is empty")
    if not all(items):
        raise ConfigError(f"--sweep {text!r}: a value is empty")
    points = tuple(tuple(v.strip() for v in item.split(":")) for item in items)
    for point in points:
        if len(point) != len(keys) or not all(point):
            raise ConfigError(
                f"--sweep {text!r}: value {':'.join(point)!r} needs {len(keys)} part(s) "
                f"separated by ':', one per key"
            )
    if len(set(points)) < len(points):
        raise ConfigError(f"--sweep {text!r} lists a value twice")
    return Axis(keys, points)


def _field(cfg: Any, key: str) -> Any:
    for name in key.split("."):
        cfg = getattr(cfg, name.replace("-", "_"))
    return cfg


def sweep_settings(base: TrainConfig, axis_texts: list[str]) -> list[Setting]:
    """The settings of the product of the ``--sweep`` axes, each checked on ``base``.

    No axis gives one empty setting (a plain sweep). Unknown keys, malformed
    or out-of-range values, keys the sweep varies itself and settings that
    would share a run name raise :class:`ConfigError` (nothing is written).
    """
    axes = [parse_axis(t) for t in axis_texts]
    keys = [k for axis in axes for k in axis.keys]
    for key in keys:
        if key in OWN_AXES:
            raise ConfigError(f"--sweep cannot vary {key!r}; use {OWN_AXES[key]}")
    if len(set(keys)) < len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise ConfigError(f"--sweep names key {dup!r} in two axes")
    settings = []
    for combo in itertools.product(*(axis.points for axis in axes)):
        raw = dict(zip(keys, (v for point in combo for v in point), strict=True))
        try:
            cfg = validate(override(base, raw))  # unknown key, wrong type, out of range
        except ConfigError as exc:
            raise ConfigError(f"--sweep: {exc}") from None
        settings.append(Setting(tuple((k, _field(cfg, k)) for k in keys)))
    names = [s.name for s in settings]
    if len(set(names)) < len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"--sweep gives two settings the same value {dup!r}")
    return settings


def axis_texts(sweeps: list[str], study: str | None) -> list[str]:
    """``--sweep`` options plus the axis of ``--study`` (if any)."""
    if study is None:
        return list(sweeps)
    if study not in STUDIES:
        raise ConfigError(f"unknown study {study!r}; use one of {', '.join(STUDIES)}")
    return [STUDIES[study], *sweeps]

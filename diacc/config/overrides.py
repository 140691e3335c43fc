"""User input into configs: :func:`override` applies dotted ``{"section.field": value}``
keys (from a TOML file, named options or ``--set`` pairs) to any config dataclass,
parsing each text by its field's type, and :func:`build_train_config` is the one place
a :class:`~diacc.config.train.TrainConfig` is assembled from user input (defaults <
TOML file < named options < ``--set`` pairs): ``diacc train``, ``diacc sweep`` and
``diacc reproduce`` all call it, so the library never goes through its own command
line. Unknown keys and ill-typed values are one-line :class:`ConfigError`\\ s; the
sections check their values themselves (:func:`diacc.fields.check_fields`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from diacc.config.train import TrainConfig, default_run_dir
from diacc.fields import ConfigError, FieldError
from diacc.sim.scenario import SCENARIO_SETTINGS, Scenario, ScenarioError, cav_slots_value


def override(config: Any, values: dict[str, Any]) -> Any:
    """Return a copy of a (nested) config dataclass with dotted keys replaced.

    ``override(TrainConfig(), {"lr": 1e-3, "reward.w_ego": 0.8})``. Unknown
    keys and values of the wrong type raise :class:`ConfigError`. Each section
    is rebuilt once with all its new values, so the checks in its
    ``__post_init__`` see them together (``psar.d_warn_m`` and
    ``psar.d_att_m`` can move in one call).
    """
    tree: dict[str, Any] = {}
    for key, value in values.items():
        *parents, leaf = key.split(".")
        node = tree
        for name in parents:
            node = node.setdefault(name, {})
            if not isinstance(node, dict):
                raise ConfigError(f"unknown config key {key!r}")
        node[leaf] = value
    return _replace(config, tree, "")


def _replace(obj: Any, tree: dict[str, Any], prefix: str) -> Any:
    # a scenario takes the keys of either kind (Release | Demand): Scenario.replace
    # refuses those its kind would ignore
    scenario = isinstance(obj, Scenario)
    names = set(SCENARIO_SETTINGS) if scenario else {f.name for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in tree.items():
        head, full_key = key.replace("-", "_"), f"{prefix}{key}"
        if head not in names:
            raise ConfigError(f"unknown config key {full_key!r}")
        current = getattr(obj, head, SCENARIO_SETTINGS.get(head))
        section = Scenario if isinstance(current, Scenario) else type(current)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[head] = _replace(current, value, f"{full_key}.")
        elif isinstance(value, dict):
            raise ConfigError(f"unknown config key {full_key + '.' + next(iter(value), '')!r}")
        elif dataclasses.is_dataclass(current) and not isinstance(value, section):
            raise ConfigError(
                f"config key {full_key!r} is a section; set its fields ({full_key}.NAME=VALUE)"
            )
        elif dataclasses.is_dataclass(current):  # a whole section, built (so checked)
            changes[head] = value
        elif scenario and head == "cav_slots":  # "every" or a cap: Demand checks it
            changes[head] = cav_slots_value(value)
        else:
            changes[head] = _coerce(_unset_as(obj, head, current), value, full_key)
    if isinstance(obj, TrainConfig) and "variant" in changes and _rederive_psar(tree):
        # a new variant derives env.use_psar again (the old one derived the current value)
        changes["env"] = dataclasses.replace(changes.get("env", obj.env), use_psar=None)
    if isinstance(obj, TrainConfig) and "run_dir" not in changes:
        if obj.run_dir == default_run_dir(obj):  # derived, not set: derive it again
            changes["run_dir"] = ""
    try:
        if scenario:  # derives a demand's count again, may change the kind
            return obj.replace(**changes)
        return dataclasses.replace(obj, **changes)
    except FieldError as exc:  # a field of this section: name it by its full key
        raise FieldError(f"{prefix}{exc.key}", exc.problem) from None
    except ScenarioError as exc:  # relations of a Scenario's fields: name the section
        raise ScenarioError(f"{prefix.rstrip('.')}: {exc}") from None


def _unset_as(obj: Any, name: str, current: Any) -> Any:
    """A value of the type a field ``X | None`` takes when it is None (unset), or an
    empty tuple field an item of its declared type, so that :func:`_coerce` parses a
    given value by it (``--set env.use_psar=false``, ``--set mix.n_vehicles=15,40``)."""
    if current is not None and current != ():
        return current
    hint = next((f.type for f in dataclasses.fields(obj) if f.name == name), None)
    if current == ():  # an empty list: an item of its declared type to parse items by
        item = str(hint).removeprefix("tuple[").split(",")[0].strip()
        return ({"int": 0, "float": 0.0}.get(item, ""),)
    kind = str(hint).split("|")[0].strip()
    return {"bool": False, "int": 0, "float": 0.0, "str": ""}.get(kind, current)


def _rederive_psar(tree: dict[str, Any]) -> bool:
    """Whether an override tree leaves ``env.use_psar`` to the variant: it sets neither
    that field nor a whole ``env`` section (an EnvConfig, which says its own)."""
    env: object = next((v for k, v in tree.items() if k.replace("-", "_") == "env"), {})
    return isinstance(env, dict) and all(k.replace("-", "_") != "use_psar" for k in env)


def _coerce(current: Any, value: Any, key: str) -> Any:
    kind = type(current)
    if kind is tuple and current and not isinstance(current[0], str):
        # of numbers (a range, mix.n_vehicles): "15,40" (--set) or a list, each item
        # parsed as the default's are
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple):
            raise ConfigError(f"config key {key!r} expects a list of numbers, got {value!r}")
        return tuple(
            _coerce(current[0], v.strip() if isinstance(v, str) else v, key) for v in items
        )
    if kind is tuple:  # of strings: "a,b" (--set) or a TOML / JSON list
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple) or not all(isinstance(v, str) for v in items):
            raise ConfigError(f"config key {key!r} expects a list of names, got {value!r}")
        return tuple(v.strip() for v in items if v.strip())
    if isinstance(value, str) and kind is not str:
        try:
            if kind is bool:
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                return value.lower() in ("true", "1")
            return kind(value)
        except ValueError:
            raise ConfigError(
                f"config key {key!r} expects {kind.__name__}, got {value!r}"
            ) from None
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ConfigError(f"config key {key!r} expects {kind.__name__}, got {value!r}")
    return value


def build_train_config(
    file: str | Path | None = None,
    *,
    variant: str | None = None,
    backend: str | None = None,
    map: str | None = None,  # noqa: A002 - the option's name
    steps: int | None = None,
    envs: int | None = None,
    seed: int | None = None,
    device: str | None = None,
    run_dir: str | Path | None = None,
    style_preset: str | None = None,
    init_from: str | Path | None = None,
    agent_slots: int | str | None = None,
    sets: Iterable[str] | Mapping[str, Any] = (),
) -> TrainConfig:
    """The training config of user input: defaults < TOML ``file`` < named options < ``sets``.

    One function for every entry point (``diacc train``, ``sweep``, ``reproduce``)
    so that they resolve settings the same way and the library never builds a
    command line to call itself. A named option left at None keeps the file's
    (or the default) value; ``steps`` is ``total_steps`` (environment steps,
    decisions x environments), ``envs`` is ``n_envs``, ``style_preset`` is
    ``env.sim.style_preset``, ``init_from`` the checkpoint a fine-tuning run starts
    from, ``agent_slots`` ``env.scenario.cav_slots`` (``"every"`` or a cap). ``sets``
    are ``KEY=VALUE`` texts (``--set``) or a mapping of dotted keys to values. All
    layers are applied in one :func:`override`, so a value one layer asks for and the
    variant contradicts (``env.use_psar``) is refused, whichever layer named the variant. Without a
    ``run_dir`` anywhere the run goes to ``runs/<variant>-<backend>-<map>-s<seed>``
    of the resolved config. Not validated here (:func:`validate` runs before a
    run writes anything); bad keys and values raise a one-line :class:`ConfigError`.
    """
    from diacc.tomlfile import read_toml

    values: dict[str, Any] = {}
    if file is not None:
        if not Path(file).exists():
            raise ConfigError(f"config file {file} does not exist")
        values.update(_flatten(read_toml(Path(file), ConfigError)))
    named = {
        "variant": variant,
        "env.backend": backend,
        "env.map": None if map is None else str(map),
        "total_steps": steps,
        "n_envs": envs,
        "seed": seed,
        "device": device,
        "run_dir": None if run_dir is None else str(run_dir),
        "env.sim.style_preset": style_preset,
        "init_from": None if init_from is None else str(init_from),
        "env.scenario.cav_slots": agent_slots,
    }
    values.update({k: v for k, v in named.items() if v is not None})
    values.update(sets if isinstance(sets, Mapping) else parse_sets(sets))
    return override(TrainConfig(), values)


def parse_sets(items: Iterable[str]) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` (``--set``) -> ``{KEY: VALUE}``; the values stay text for
    :func:`override` to parse by the field's type (a later KEY wins)."""
    values: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        values[key] = value
    return values


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested TOML tables -> dotted keys (``{"env": {"map": m}}`` -> ``{"env.map": m}``)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping) and value:  # an empty one stays for override to judge
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out

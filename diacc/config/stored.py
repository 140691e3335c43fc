"""Stored configs (a checkpoint's, a run's ``config.json``) read back: the schema
version they were written with (:data:`CONFIG_SCHEMA`) and the steps that migrate an
older one, so that loading never switches how a trained policy was run."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from diacc.config.overrides import override
from diacc.config.train import PAPER_LEARNER, TrainConfig
from diacc.fields import ConfigError

#: Version of the config schema a checkpoint stores (its ``config_schema``; a config
#: without one is version 1). Raise it whenever a field moves or its default changes,
#: and add the step that rewrites a stored config of the version before into the new
#: one to :data:`_MIGRATIONS`, so that loading never switches how a trained policy
#: was run (docs/concepts/conventions.md, "Configuration").
CONFIG_SCHEMA = 3

#: Sections a TrainConfig held at its top level before it nested an EnvConfig.
_ENV_SECTIONS_BEFORE_NESTING = ("backend", "map", "sim", "scenario", "obs", "psar", "reward")
#: Defaults of version 1 that version 2 changed; a version-1 config without the field
#: meant these: ``env.psar.horizon`` ("stopping"), ``env.psar.full_brake`` ("bound"),
#: the learner's sizes, minibatches and entropy bonus (:data:`PAPER_LEARNER`).
_SCHEMA_1_DEFAULTS = {
    "env.psar.horizon": "stopping",
    "env.psar.full_brake": "bound",
    **PAPER_LEARNER,
}


def _schema_1_to_2(flat: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2 of a flat stored config: the environment's sections move under
    ``env`` (configs that predate the nesting), a missing field takes its version-1
    default."""
    if not any(key.split(".")[0] == "env" for key in flat):
        flat = {
            f"env.{key}" if key.split(".")[0] in _ENV_SECTIONS_BEFORE_NESTING else key: value
            for key, value in flat.items()
        }
    return {**_SCHEMA_1_DEFAULTS, **flat}


#: ``env.scenario.cav_slots`` before version 3, when it was a cap for every scenario.
_SCHEMA_2_CAV_SLOTS = 16


def _schema_2_to_3(flat: dict[str, Any]) -> dict[str, Any]:
    """Version 2 -> 3: ``env.scenario.cav_slots`` became ``"every"`` by default. A demand
    stored without it was capped at 16 slots and keeps the cap; a release stored with the
    old default 16 (configs of when both kinds were one class) drops the demand setting
    it never used."""
    kind = flat.get("env.scenario.kind", "release")
    if kind == "demand":
        return {"env.scenario.cav_slots": _SCHEMA_2_CAV_SLOTS, **flat}
    if flat.get("env.scenario.cav_slots") == _SCHEMA_2_CAV_SLOTS:
        return {key: value for key, value in flat.items() if key != "env.scenario.cav_slots"}
    return flat


#: version -> the step that rewrites a stored config of that version (flat: dotted keys)
#: into the next.
_MIGRATIONS = {1: _schema_1_to_2, 2: _schema_2_to_3}


def stored_config(stored: dict[str, Any], schema: Any = 1) -> TrainConfig:
    """The TrainConfig a stored config of ``schema`` means (one-line ConfigError if none).

    Migrated step by step to :data:`CONFIG_SCHEMA`; a field it lacks then takes its
    current default. Values pass the same checks (ranges, bounds, contradictions) as
    any user input.
    """
    if not isinstance(schema, int) or isinstance(schema, bool) or schema < 1:
        raise ConfigError(f"config schema must be a positive integer, got {schema!r}")
    if schema > CONFIG_SCHEMA:
        raise ConfigError(
            f"config schema {schema} is newer than this diacc's ({CONFIG_SCHEMA}); update diacc"
        )
    flat = flatten_config(stored)
    for version in range(schema, CONFIG_SCHEMA):
        flat = _MIGRATIONS[version](flat)
    return override(TrainConfig(), flat)


def flatten_config(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists as tuples), the keys :func:`override` takes."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return flat

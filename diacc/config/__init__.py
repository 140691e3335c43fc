"""Typed configuration. Defaults follow the DIACC paper and, where it is silent, the
authors' public predecessor environment (lzxphhh/HARL-based_simulator); the learner's
sizes are the measured cheaper ones (:class:`ModelConfig`; the paper's are
:data:`PAPER_LEARNER`, ``configs/paper-learner.toml``).

Configs are frozen dataclasses so that a run's settings cannot drift after
start-up; ``dataclasses.replace`` makes variants. One tree: a :class:`TrainConfig`
nests one :class:`EnvConfig`, which nests the simulator's sections
(:class:`~diacc.sim.settings.SimConfig`, :class:`~diacc.sim.scenario.Scenario`; they
live in :mod:`diacc.sim`, which never imports this package). Checked in one way:

* each field's range or choices sit next to it (:func:`~diacc.fields.ranged`,
  :func:`~diacc.fields.one_of`) and are checked, every float finite, when its section
  is built (:func:`diacc.fields.check_fields`), with the relations within a section;
* a value the config derives (``env.use_psar`` from the variant, a demand's vehicle
  count, ``run_dir``) is derived when unset and, when given and contradicted, refused
  with a one-line :class:`ConfigError`, never overwritten;
* :func:`validate` adds the relations a training run needs, before it writes anything.

Modules: :mod:`~diacc.config.env` (the environment's sections),
:mod:`~diacc.config.train` (the trainer's), :mod:`~diacc.config.mix` (the training
mix, ``[mix]``), :mod:`~diacc.config.overrides` (user
input: :func:`override`, :func:`build_train_config`), :mod:`~diacc.config.stored`
(checkpoints' configs and their schema version), :mod:`~diacc.config.checks`
(:func:`validate`). Everything users import is importable from here.
"""

from __future__ import annotations

from diacc.config.checks import _leaves, rollout_bytes, train_slots, validate  # noqa: F401
from diacc.config.env import (  # noqa: F401 - re-exported
    CLOSENESS_MODES,
    EXIT_BONUS_SCALES,
    FORCE_BRAKE_MODES,
    FULL_BRAKE_MODES,
    HORIZON_MODES,
    LATERAL_FRAMES,
    PSAR_ACTION_MODES,
    EnvConfig,
    EventConfig,
    ObservationConfig,
    PSARConfig,
    RewardConfig,
    resolve_road,
)
from diacc.config.mix import MixConfig  # noqa: F401
from diacc.config.overrides import build_train_config, override, parse_sets  # noqa: F401
from diacc.config.stored import CONFIG_SCHEMA, flatten_config, stored_config  # noqa: F401
from diacc.config.train import (  # noqa: F401 - re-exported
    ACTION_MODES,
    PAPER_LEARNER,
    PAPER_VARIANTS,
    VARIANT_TABLE,
    VARIANTS,
    ModelConfig,
    TrainConfig,
    Variant,
    default_run_dir,
)
from diacc.fields import (  # noqa: F401 - re-exported
    MAX_ENVS,
    MAX_EPISODE_STEPS,
    MAX_EPOCHS,
    MAX_HEADS,
    MAX_HISTORY_STEPS,
    MAX_NEIGHBOURS,
    MAX_NETWORK_DIM,
    MAX_ROLLOUT_BYTES,
    MAX_SUBSTEPS,
    MAX_VEHICLES,
    ConfigError,
    one_of,
    ranged,
)
from diacc.sim.drivers import (  # noqa: F401 - re-exported
    PRESET_REDUCTION_SPEED_MPS,
    STYLE_PRESETS,
    DriverStyle,
    preset_road,
)
from diacc.sim.scenario import (  # noqa: F401 - re-exported
    AGGRESSIVE,
    CAUTIOUS,
    CAV_STYLE,
    NORMAL,
    STYLE_MIXES,
    STYLE_NAMES,
    Scenario,
    ScenarioError,
)
from diacc.sim.settings import (  # noqa: F401
    BACKENDS,
    BATCHED_BACKENDS,
    CAV_MODES,
    HIGHWAY_MERGES,
    ON_COLLISION,
    CavParams,
    SimConfig,
)

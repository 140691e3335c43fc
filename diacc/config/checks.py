"""The relations between a training config's fields that only a run needs
(:func:`validate`, called before a run writes anything), the memory estimate it
bounds (:func:`rollout_bytes`) and the agent slots of a run's envs (:func:`train_slots`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from diacc.config.mix import corner_scenarios
from diacc.config.train import TrainConfig
from diacc.errors import MapError
from diacc.fields import MAX_ROLLOUT_BYTES, ConfigError
from diacc.sim.maps import load_map
from diacc.sim.settings import BATCHED_BACKENDS


def train_slots(cfg: TrainConfig) -> int:
    """Agent slots C of every env of a run: ``env.scenario``'s, or with a mix the most
    any of its cells has (the envs of a cell with fewer are padded with slots that never
    hold a CAV)."""
    if not cfg.mix.on:
        return cfg.env.scenario.n_slots
    return max(s.n_slots for s in corner_scenarios(cfg.mix, cfg.env.scenario))


def rollout_bytes(cfg: TrainConfig) -> int:
    """Upper estimate of the bytes a rollout's observations take (the memory bound of
    :func:`validate`), without building anything.

    Counts every value of :mod:`diacc.envs.observation`'s layout as 8 bytes and a
    node as 8 features (the layout has 6), so that it stays above the real size
    (``ObservationSpec.actor_shapes`` / ``critic_shapes``; a test keeps it so):
    per CAV slot its own and K neighbours' (HDV and CAV) T-step histories, masks and
    lane and road tables; per env the critic's ``max_vehicles`` rows.
    """
    obs = cfg.env.obs
    k, t = obs.n_neighbours, obs.history_steps
    per_slot = (2 * k + 1) * t * 8 + 3 * k + 64
    per_env = obs.max_vehicles * (2 * k + 8) + 16
    per_step = max(1, train_slots(cfg)) * per_slot + per_env
    return 8 * cfg.rollout_steps * cfg.n_envs * per_step


def validate(cfg: TrainConfig) -> TrainConfig:
    """Reject settings that cannot train together (one-line ConfigError).

    Each field's own range, finiteness and choices are checked when the config
    is built (:func:`ranged`, :func:`one_of`, the sections' ``__post_init__``);
    what is left are relations between fields that only a training run needs.
    Called before a run writes anything, so a bad value never leaves a run
    directory behind or surfaces later as a NaN checkpoint or a torch error.
    """
    if rollout_bytes(cfg) > MAX_ROLLOUT_BYTES:
        raise ConfigError(
            f"the rollout's observations would take about {rollout_bytes(cfg) / 2**30:.3g} GiB "
            f"(rollout_steps {cfg.rollout_steps} x n_envs {cfg.n_envs} x "
            f"{train_slots(cfg)} CAV slots, env.obs n_neighbours "
            f"{cfg.env.obs.n_neighbours}, history_steps {cfg.env.obs.history_steps}, "
            f"max_vehicles {cfg.env.obs.max_vehicles}); at most "
            f"{MAX_ROLLOUT_BYTES / 2**30:g} GiB, a third of a 24 GiB machine"
        )
    if cfg.mix.on:
        _check_mix(cfg)
    elif cfg.env.scenario.n_cavs < 1:
        raise ConfigError(
            f"env.scenario: {cfg.env.scenario.n_vehicles} vehicles at cav_penetration "
            f"{cfg.env.scenario.cav_penetration} make 0 CAVs; training needs at least one"
        )
    if cfg.total_steps < cfg.rollout_steps * cfg.n_envs:
        # An update collects rollout_steps x n_envs steps: a smaller budget would
        # run one update far past it.
        raise ConfigError(
            f"total_steps {cfg.total_steps} is less than one update "
            f"(rollout_steps {cfg.rollout_steps} x n_envs {cfg.n_envs} = "
            f"{cfg.rollout_steps * cfg.n_envs} steps)"
        )
    if cfg.vector == "batched" and cfg.env.backend not in BATCHED_BACKENDS:
        raise ConfigError(
            f"vector 'batched' steps every env in one simulator, which backend "
            f"{cfg.env.backend!r} does not have ({', '.join(BATCHED_BACKENDS)} does); "
            "use vector auto, sync or process"
        )
    if cfg.env.psar_actions != "proposed" and not cfg.env.use_psar:
        raise ConfigError(
            f"env.psar_actions {cfg.env.psar_actions!r} needs PSAR, which variant "
            f"{cfg.variant!r} does not use"
        )
    if cfg.credit == "own" and cfg.critic_values != "per_agent":
        raise ConfigError(
            "credit 'own' gives each CAV its own reward, which needs a value per CAV: "
            "set critic_values=per_agent"
        )
    if cfg.init_from and not Path(cfg.init_from).is_file():
        raise ConfigError(f"init_from: checkpoint {cfg.init_from} does not exist")
    if cfg.rollout_steps % cfg.chunk_len:
        raise ConfigError(
            f"rollout_steps {cfg.rollout_steps} must be a multiple of chunk_len {cfg.chunk_len}"
        )
    if cfg.rollout_steps < cfg.env.sim.episode_steps:
        # Every update restarts the environments: a shorter rollout would never
        # reach (nor train on) the ends of episodes.
        raise ConfigError(
            f"rollout_steps {cfg.rollout_steps} must be >= env.sim.episode_steps "
            f"{cfg.env.sim.episode_steps}, so that rollouts hold whole episodes"
        )
    maps = (cfg.env.map, *cfg.extra_maps)
    if len(maps) > cfg.n_envs:
        raise ConfigError(
            f"{len(maps)} training maps ({', '.join(maps)}) need at least as many envs, "
            f"got n_envs {cfg.n_envs}"
        )
    sequences = cfg.n_envs * (cfg.rollout_steps // cfg.chunk_len)
    if cfg.minibatches > sequences:
        # A minibatch is at least one whole (chunk, env) sequence.
        raise ConfigError(
            f"minibatches {cfg.minibatches} exceeds the rollout's {sequences} sequences "
            f"(n_envs {cfg.n_envs} x rollout_steps {cfg.rollout_steps} / chunk_len "
            f"{cfg.chunk_len}); set minibatches <= {sequences} or raise n_envs or rollout_steps"
        )
    return cfg


def _check_mix(cfg: TrainConfig) -> None:
    """The relations of a training mix (``cfg.mix``) with the rest of the config: its maps
    exist, its blocks have envs, and every cell it can draw has a CAV and fits the
    critic's ``env.obs.max_vehicles`` rows."""
    mix = cfg.mix
    if cfg.extra_maps:
        raise ConfigError(
            "extra_maps and mix.maps both split the envs over maps; list every map in mix.maps"
        )
    if mix.blocks > cfg.n_envs:
        raise ConfigError(
            f"mix.blocks {mix.blocks} needs at least as many envs, got n_envs {cfg.n_envs}"
        )
    for road_map in dict.fromkeys(mix.map_names()):
        try:
            load_map(road_map)
        except MapError as exc:
            raise ConfigError(f"mix.maps: {exc}") from None
    cap = cfg.env.obs.max_vehicles
    for scenario in corner_scenarios(mix, cfg.env.scenario):
        if scenario.n_vehicles > cap:
            what = (
                f"mix.n_vehicles up to {scenario.n_vehicles}"
                if scenario.kind == "release"
                else f"a demand of mix.inflow_vph {scenario.inflow_vph:g} x mix.demand_s "
                f"{scenario.demand_s:g} s ({scenario.n_vehicles} vehicles)"
            )
            raise ConfigError(
                f"{what} exceeds env.obs.max_vehicles {cap}, the critic's rows; "
                "narrow the mix or raise max_vehicles"
            )
        if scenario.n_cavs < 1:
            raise ConfigError(
                f"mix: a {scenario.kind} of {scenario.n_vehicles} vehicles at cav_penetration "
                f"{scenario.cav_penetration:g} makes 0 CAVs; training needs at least one "
                "(raise the low end of mix.cav_penetration, n_vehicles or inflow_vph)"
            )


def _leaves(obj: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted key, value) of every non-dataclass field; tuples give one leaf per item."""
    out = []
    for f in dataclasses.fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += _leaves(value, f"{key}.")
        elif isinstance(value, tuple):
            out += [(f"{key}[{i}]", v) for i, v in enumerate(value)]
        else:
            out.append((key, value))
    return out

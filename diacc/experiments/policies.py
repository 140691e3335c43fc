"""Policies the evaluator runs: non-learning baselines, scripted CAVs, checkpoints and a
user's own controller (``package.module:factory``, :mod:`diacc.experiments.userpolicy`).

Every policy answers the same two questions, and every episode is played
through the environment (:mod:`diacc.envs.episode`), so the evaluator treats a
baseline exactly like a checkpoint:

* :meth:`Policy.env_config`: which environment a grid cell means for it
  (``pure-hdv`` turns every CAV into an HDV and redraws the styles of all;
  ``same-mix`` keeps the cell's draw and hands the CAV slots to human
  drivers of one style, so that it differs from a CAV policy in the control
  only; ``cooperative`` lets the CAVs drive themselves; a checkpoint keeps
  the observation, PSAR, reward and simulation settings it was trained with);
* :meth:`Policy.act`: the CAVs' actions; from a trained actor with its GRU
  state, greedy (argmax, the default) or, with ``PolicySpec.sampled``, drawn
  from the policy's distribution with a generator seeded by the episode seed
  (the stochastic policy that training optimised; an under-trained actor's
  argmax can repeat one suppressed action forever, e.g. ``accelerate`` while
  standing at a lane end, which sampling does not); ``remain`` for the
  baselines, whose CAVs do not exist or drive themselves (PSAR is off for them).

Policies are built from a :class:`PolicySpec` (a name or a checkpoint path),
which is what crosses process boundaries: each worker loads its own copy.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.config import (
    STYLE_NAMES,
    VARIANTS,
    EnvConfig,
    TrainConfig,
)
from diacc.envs.actions import ACCELERATE, ACTION_NAMES, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.observation import ActorObs
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.userpolicy import Controller, is_user_spec
from diacc.shipped import shipped_checkpoint, shipped_checkpoints
from diacc.sim.maps import Map

#: Names of the non-learning baselines. ``same-mix`` drives the CAV slots by the
#: ``normal`` human model; ``same-mix:<style>`` by another style (:data:`STYLE_NAMES`).
BASELINES = ("pure-hdv", "same-mix", "cooperative")
SAME_MIX = "same-mix"
#: Style of the human drivers in the CAV slots of plain ``same-mix``.
SAME_MIX_DEFAULT_STYLE = "normal"
#: Scripted CAV policies: one fixed action, uniform random, the ``heuristic`` or
#: ``late-merge`` (:class:`ScriptedPolicy`). ``<name>-nopsar`` runs the same script
#: without PSAR.
SCRIPTED = ("remain", "accelerate", "random", "heuristic", "late-merge")
#: The heuristic leaves a lane that ends within this distance ahead (m): on the
#: paper's maps (release in the first 200 m, drop at 500 m) as soon as it is
#: released. Merging early spreads the merges over the road; at 150 m CAVs
#: queued at the drop (train-50, 100 % CAVs, headway PSAR, highway, 2 episodes:
#: delay -7 % against pure HDV at 150 m, -26 % at 300 m, -51 % at 400 m).
HEURISTIC_LEAVE_M = 400.0
#: ``late-merge`` keeps its lane (accelerating) until its lane ends within this distance
#: ahead (m), then asks for the surviving side: the late, zipper-style merge traffic
#: engineers recommend in congestion, and the probe of lane-end liveness (issue 44).
LATE_MERGE_LEAVE_M = 150.0


class PolicyError(DiaccError, ValueError):
    """Unknown policy name or unusable checkpoint for evaluation; one line."""


def action_mode(sampled: bool) -> str:
    """The ``--actions`` name (:data:`~diacc.config.ACTION_MODES`) of a checkpoint's mode."""
    return "sampled" if sampled else "greedy"


@dataclass(frozen=True)
class PolicySpec:
    """Picklable reference to a policy: a baseline name or a checkpoint path.

    Args:
        name: ``pure-hdv``, ``cooperative`` or the path of a ``checkpoint.pt``.
        variant: if set, a checkpoint must be of this variant (guards against
            comparing the wrong runs).
        sampled: a checkpoint samples its actions instead of taking the argmax.
    """

    name: str
    variant: str | None = None
    sampled: bool = False

    @property
    def is_baseline(self) -> bool:
        return self.name in BASELINES or self.name.startswith(f"{SAME_MIX}:")

    @property
    def is_scripted(self) -> bool:
        return self.name.removesuffix("-nopsar") in SCRIPTED

    @property
    def is_python(self) -> bool:
        """A user's controller, ``package.module:factory`` (:mod:`.userpolicy`)."""
        return not self.is_baseline and is_user_spec(self.name)


class Policy:
    """Base class; see the module docstring."""

    label: str = ""
    #: Settings shared by every cell (simulation, observation, PSAR, reward).
    base: EnvConfig = EnvConfig()

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        """The environment of one grid cell for this policy.

        Observations are padded to at least the cell's vehicles: only a
        checkpoint's networks fix ``max_vehicles`` (:class:`CheckpointPolicy`
        refuses larger cells).
        """
        obs = self.base.obs
        scenario = settings.apply_slots(cell.scenario(base=self.base.scenario))
        return dataclasses.replace(
            self.base,
            backend=settings.backend,
            map=cell.map,
            scenario=scenario,
            sim=settings.apply(self.base.sim),
            psar=settings.apply_psar(self.base.psar),
            obs=dataclasses.replace(obs, max_vehicles=max(obs.max_vehicles, scenario.n_vehicles)),
        )

    def use_road(self, road: Map) -> None:
        """The road of the episodes to come (:class:`~diacc.envs.episode.EpisodeDriver`
        calls it)."""

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        """Forget any recurrent state (called before the first :meth:`act`)."""

    def act(self, actor_obs: ActorObs, first_step: bool | np.ndarray) -> np.ndarray:
        """(C,) int64 actions for every CAV slot; here ``remain``, i.e. no command.

        ``first_step``: True at the episode's first step, or a (C,) mask of the slots
        whose CAV acts for the first time (slots refilled in a demand scenario).
        """
        return np.full(actor_obs.alive.shape[0], REMAIN, np.int64)

    def describe(self) -> dict:
        """What identifies this policy in a results directory's ``meta.json``."""
        return {"policy": self.label}


class PureHdvPolicy(Policy):
    """Every vehicle is an HDV (IDM + MOBIL / LC2013 with its safety model on)."""

    label = "pure-hdv"

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        cfg = super().env_config(cell, settings)
        return dataclasses.replace(
            cfg, use_psar=False, scenario=cell.scenario(cav_penetration=0.0, base=cfg.scenario)
        )


def same_mix_style(name: str) -> str:
    """The style of a ``same-mix`` / ``same-mix:<style>`` name (one-line error if unknown)."""
    style = SAME_MIX_DEFAULT_STYLE if name == SAME_MIX else name.removeprefix(f"{SAME_MIX}:")
    if (name != SAME_MIX and not name.startswith(f"{SAME_MIX}:")) or style not in STYLE_NAMES:
        raise PolicyError(
            f"unknown policy {name!r}; the same-mix baseline is {SAME_MIX} "
            f"({SAME_MIX_DEFAULT_STYLE} drivers) or {SAME_MIX}:<style> with style one of "
            f"{', '.join(STYLE_NAMES)}"
        )
    return style


class SameMixPolicy(Policy):
    """The cell's own vehicles and seeds, its CAV slots driven by human drivers.

    Pure HDV redraws the styles of all N vehicles, so it differs from a CAV
    policy in the vehicle mix as well as in the control (with ``paper``
    presets, e.g., in the number of cautious drivers who get stuck at a lane
    end). Here the draw is the CAV policy's (:attr:`Scenario.cav_slot_style`):
    the same HDVs in the same slots, and in each CAV slot a human driver of
    one style (``normal`` unless named), with no PSAR. A CAV policy's gain
    over this baseline is what its control changes.
    """

    def __init__(self, name: str = SAME_MIX) -> None:
        self.style = same_mix_style(name)
        self.label = name

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        cfg = super().env_config(cell, settings)
        scenario = dataclasses.replace(cfg.scenario, cav_slot_style=self.style)
        return dataclasses.replace(cfg, use_psar=False, scenario=scenario)


class CooperativePolicy(Policy):
    """CAVs drive themselves: CACC car following and cooperative lane changes.

    On SUMO the CAVs are CACC vehicles with ``lcCooperative = 1``; on highway
    they run the HDV IDM/MOBIL code with a CACC-like parameter set (see
    :class:`~diacc.sim.backends.highway.backend.HighwayBackend`).
    """

    label = "cooperative"

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        cfg = super().env_config(cell, settings)
        return dataclasses.replace(
            cfg, use_psar=False, sim=dataclasses.replace(cfg.sim, cav_mode="cooperative")
        )


class ScriptedPolicy(Policy):
    """CAVs that always take one action (``remain``, ``accelerate``), a uniform
    random one (``random``, seeded by the episode seed) or follow the
    ``heuristic``, with or without PSAR.

    The first three are the probes of ``diacc bench --safety``: what PSAR and
    the simulators make of a policy that knows nothing about traffic. The
    heuristic is the simplest sensible driver, a bar for a learned one:
    accelerate, and once the own lane ends within :data:`HEURISTIC_LEAVE_M`,
    ask for the neighbouring lane that survives longer (PSAR turns the
    request into ``remain``/``decelerate`` while the gap is unsafe). It reads
    what the actor observes (own position and lane) and the static map.
    ``late-merge`` is the heuristic that keeps its lane until
    :data:`LATE_MERGE_LEAVE_M` before the lane end: it queues at the end of
    its lane, so it gets through only if the target lane lets it in. It
    accelerates rather than ``remain``: ``remain`` keeps the target speed,
    so a CAV that PSAR once stopped would stand for good by its own choice.
    """

    def __init__(self, name: str) -> None:
        script = name.removesuffix("-nopsar")
        if script not in SCRIPTED:
            raise PolicyError(f"unknown scripted policy {name!r}; known: {', '.join(SCRIPTED)}")
        self.label = name
        self.script = script
        self.base = dataclasses.replace(EnvConfig(), use_psar=not name.endswith("-nopsar"))
        self._rng = np.random.default_rng(0)
        self._road: Map | None = None

    def use_road(self, road: Map) -> None:
        self._road = road

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        self._rng = np.random.default_rng([int(seed), 0x5C21])

    def act(self, actor_obs: ActorObs, first_step: bool | np.ndarray) -> np.ndarray:
        n_cavs = actor_obs.alive.shape[0]
        if self.script == "random":
            return self._rng.integers(0, len(ACTION_NAMES), n_cavs).astype(np.int64)
        if self.script == "heuristic":
            if self._road is None:
                raise PolicyError("the heuristic needs the road: call use_road() first")
            return heuristic_actions(actor_obs, self._road)
        if self.script == "late-merge":
            if self._road is None:
                raise PolicyError("late-merge needs the road: call use_road() first")
            return heuristic_actions(actor_obs, self._road, LATE_MERGE_LEAVE_M)
        return np.full(n_cavs, ACTION_NAMES.index(self.script), np.int64)


def heuristic_actions(
    actor_obs: ActorObs,
    road: Map,
    leave_m: float = HEURISTIC_LEAVE_M,
    cruise: int = ACCELERATE,
) -> np.ndarray:
    """(C,) actions of the heuristic (``late-merge``: ``leave_m`` and ``cruise``
    changed; see :class:`ScriptedPolicy`).

    Position and lane come from the observation (``self_state`` x / route
    length and lane / (max_lanes - 1)); the map says where each lane ends
    (:meth:`Map.lane_end_m`) and on which side lanes drop (``drop_side``).
    A CAV whose lane ends within ``leave_m`` asks for the
    neighbouring lane away from the drop side, which leads to the surviving
    lanes even where that neighbour ends at the same point (the outer lane
    of a 4 -> 2 drop goes over the inner one).
    """
    lane_norm = max(road.max_lanes - 1, 1)
    x_m = actor_obs.self_state[:, 0].astype(np.float64) * road.length_m  # (C,)
    lane = np.rint(actor_obs.self_state[:, 4] * lane_norm).astype(np.int64)  # (C,)
    lane = np.clip(lane, 0, road.max_lanes - 1)
    segment = road.segment_of(x_m)  # (C,)
    leave = road.lane_end_m()[segment, lane] - x_m < leave_m  # (C,)
    offset = -1 if road.drop_side == "left" else +1  # towards the surviving lanes
    target = lane + offset  # (C,)
    in_range = (target >= 0) & (target < road.max_lanes)
    exists = in_range & road.lane_exists()[segment, np.clip(target, 0, road.max_lanes - 1)]
    side = LANE_RIGHT if offset < 0 else LANE_LEFT
    return np.where(leave & exists & actor_obs.alive, side, cruise).astype(np.int64)


class UserPolicy(Policy):
    """A user's controller on PettingZoo observations, under PSAR like the heuristic
    (:mod:`diacc.experiments.userpolicy`)."""

    def __init__(self, spec: str) -> None:
        self.label = spec
        self.controller = Controller(spec)
        self._env = None

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        """As every policy's; also tells the controller the cell its errors name and its
        time limit (every command asks for a cell's environment before playing it)."""
        self.controller.cell = cell.key
        self.controller.timeout_s = settings.controller_timeout_s
        return super().env_config(cell, settings)

    def use_env(self, env) -> None:
        """The environment of the episodes to come (its agents and observation space)."""
        self._env = env

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        self.controller.reset(seed)

    def act(self, actor_obs: ActorObs, first_step: bool | np.ndarray) -> np.ndarray:
        if self._env is None:
            raise PolicyError(f"{self.label} needs its environment: call use_env() first")
        return self.controller.actions(self._env, actor_obs)

    def describe(self) -> dict:
        return {"policy": self.label, "controller": self.label}


class CheckpointPolicy(Policy):
    """A trained actor, greedy or sampling, with PSAR if its variant uses PSAR."""

    def __init__(self, path: str | Path, variant: str | None = None, sampled: bool = False) -> None:
        import torch

        from diacc.learn.checkpoint import load_actor

        self.path = Path(path)
        if variant is not None and variant not in VARIANTS:
            raise PolicyError(f"unknown variant {variant!r}; known: {', '.join(VARIANTS)}")
        self.actor, cfg, payload = load_actor(self.path, variant)
        self.train_config: TrainConfig = cfg
        self.hidden_size = cfg.model.gru_hidden
        self.base = cfg.env  # use_psar as the variant says (VARIANT_TABLE)
        self.sampled = sampled
        self.label = f"{cfg.variant} (sampled)" if sampled else cfg.variant
        self.update = int(payload.get("update", 0))
        self.global_step = int(payload.get("global_step", 0))
        self._hidden = torch.zeros(0, self.hidden_size)
        self._generator = torch.Generator()

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        scenario = cell.scenario(base=self.base.scenario)
        n_vehicles = scenario.n_vehicles
        # A demand critic holds the vehicles on the road only (compact rows), not all N.
        if scenario.kind != "demand" and n_vehicles > self.base.obs.max_vehicles:
            raise PolicyError(
                f"cell {cell.key} has {n_vehicles} vehicles but checkpoint {self.path} "
                f"observes at most {self.base.obs.max_vehicles}"
            )
        return super().env_config(cell, settings)

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        import torch

        self._hidden = torch.zeros(n_cavs, self.hidden_size)
        self._generator.manual_seed(seed)

    def act(self, actor_obs: ActorObs, first_step: bool | np.ndarray) -> np.ndarray:
        import torch

        from diacc.learn.acting import decide
        from diacc.learn.models.inputs import to_tensors

        n_cavs = actor_obs.alive.shape[0]
        if n_cavs == 0:  # a cell without CAVs (rho = 0): the networks take no empty batch
            return np.zeros(0, np.int64)
        start = torch.as_tensor(np.broadcast_to(first_step, (n_cavs,)).copy())  # (C,) bool
        step = decide(
            self.actor, to_tensors(actor_obs), self._hidden, start, self.sampled, self._generator
        )
        self._hidden = step.hidden  # (C, H)
        return step.action.cpu().numpy().astype(np.int64)  # (C,)

    def describe(self) -> dict:
        return {
            "policy": self.label,
            "checkpoint": str(self.path.resolve()),
            "update": self.update,
            "actions": action_mode(self.sampled),
            "trained_on": self.train_config.env.backend,
            "trained_steps": self.global_step,  # budget, shown in table captions
            "total_steps": self.train_config.total_steps,
        }


def parse_policy(name: str, variant: str | None = None, sampled: bool = False) -> PolicySpec:
    """Check a ``--policy`` value: a baseline name or an existing checkpoint file."""
    if name.startswith(f"{SAME_MIX}:"):
        same_mix_style(name)
    spec = PolicySpec(name)
    if spec.is_baseline or spec.is_scripted or spec.is_python:
        if variant is not None:
            what = name if spec.is_python else f"the {name} baseline"
            raise PolicyError(f"--variant applies to checkpoints, not to {what}")
        if sampled:
            raise PolicyError(f"--actions sampled applies to checkpoints, not to {name}")
        if spec.is_python:
            build_policy(spec)  # one-line error for a bad module or factory, here
        return spec
    path = Path(name)
    if not path.exists():  # a shipped agent by name, from any working directory
        path = shipped_checkpoint(name) or path
    if path.is_dir():
        if not (path / "checkpoint.pt").exists():
            raise PolicyError(f"run directory {path} has no checkpoint.pt")
        path = path / "checkpoint.pt"
    if path.suffix != ".pt" and not path.exists():
        raise PolicyError(
            f"unknown policy {name!r}; use {', '.join(BASELINES + SCRIPTED)} (scripted ones also "
            f"as <name>-nopsar, {SAME_MIX}:<style>), the path of a checkpoint.pt, a shipped "
            f"checkpoint ({', '.join(shipped_checkpoints())}) or a Python controller as "
            "package.module:factory"
        )
    if not path.exists():
        raise PolicyError(f"checkpoint {path} does not exist")
    return PolicySpec(str(path), variant, sampled)


def build_policy(spec: PolicySpec) -> Policy:
    """Instantiate the policy a spec names (loads checkpoints)."""
    if spec.name == "pure-hdv":
        return PureHdvPolicy()
    if spec.name == "cooperative":
        return CooperativePolicy()
    if spec.name == SAME_MIX or spec.name.startswith(f"{SAME_MIX}:"):
        return SameMixPolicy(spec.name)
    if spec.is_scripted:
        return ScriptedPolicy(spec.name)
    if spec.is_python:
        return UserPolicy(spec.name)
    return CheckpointPolicy(spec.name, spec.variant, spec.sampled)

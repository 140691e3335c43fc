"""Policies the evaluator runs: two non-learning baselines, scripted CAVs and checkpoints.

Every policy answers the same two questions, and every episode is played
through the environment (:mod:`diacc.episode`), so the evaluator treats a
baseline exactly like a checkpoint:

* :meth:`Policy.env_config`: which environment a grid cell means for it
  (``pure-hdv`` turns every CAV into an HDV; ``cooperative`` lets the CAVs
  drive themselves; a checkpoint keeps the observation, PSAR, reward and
  simulation settings it was trained with);
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

from diacc.actions import ACTION_NAMES, REMAIN
from diacc.config import VARIANTS, EnvConfig, SimConfig, TrainConfig
from diacc.errors import DiaccError
from diacc.grid import Cell
from diacc.observation import ActorObs

#: Names of the non-learning baselines.
BASELINES = ("pure-hdv", "cooperative")
#: Scripted CAV policies (safety benchmark): one fixed action, or uniform random.
#: ``<name>-nopsar`` runs the same script without PSAR.
SCRIPTED = ("remain", "accelerate", "random")


class PolicyError(DiaccError, ValueError):
    """Unknown policy name or unusable checkpoint for evaluation; one line."""


@dataclass(frozen=True)
class EvalSettings:
    """Evaluation-wide overrides of a policy's own simulation settings (None = keep)."""

    backend: str = "highway"
    episode_steps: int | None = None
    style_preset: str | None = None

    def __post_init__(self) -> None:
        if self.episode_steps is not None and self.episode_steps < 1:
            raise PolicyError(f"episode_steps must be >= 1, got {self.episode_steps}")

    def apply(self, sim: SimConfig) -> SimConfig:
        changes = {}
        if self.episode_steps is not None:
            changes["episode_steps"] = self.episode_steps
        if self.style_preset is not None:
            changes["style_preset"] = self.style_preset
        return dataclasses.replace(sim, **changes)

    def describe(self) -> dict:
        """What an evaluation's ``meta.json`` records of these settings (and checks on reuse)."""
        return {
            "backend": self.backend,
            "settings": {"episode_steps": self.episode_steps, "style_preset": self.style_preset},
        }


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
        return self.name in BASELINES

    @property
    def is_scripted(self) -> bool:
        return self.name.removesuffix("-nopsar") in SCRIPTED


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
        return dataclasses.replace(
            self.base,
            backend=settings.backend,
            map=cell.map,
            scenario=cell.scenario(base=self.base.scenario),
            sim=settings.apply(self.base.sim),
            obs=dataclasses.replace(obs, max_vehicles=max(obs.max_vehicles, cell.n_vehicles)),
        )

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        """Forget any recurrent state (called before the first :meth:`act`)."""

    def act(self, actor_obs: ActorObs, first_step: bool) -> np.ndarray:
        """(C,) int64 actions for every CAV slot; here ``remain``, i.e. no command."""
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


class CooperativePolicy(Policy):
    """CAVs drive themselves: CACC car following and cooperative lane changes.

    On SUMO the CAVs are CACC vehicles with ``lcCooperative = 1``; on highway
    they run the HDV IDM/MOBIL code with a CACC-like parameter set (see
    :class:`~diacc.backends.highway.backend.HighwayBackend`).
    """

    label = "cooperative"

    def env_config(self, cell: Cell, settings: EvalSettings) -> EnvConfig:
        cfg = super().env_config(cell, settings)
        return dataclasses.replace(
            cfg, use_psar=False, sim=dataclasses.replace(cfg.sim, cav_mode="cooperative")
        )


class ScriptedPolicy(Policy):
    """CAVs that always take one action (``remain``, ``accelerate``) or a uniform
    random one (``random``, seeded by the episode seed), with or without PSAR.

    These are the probes of ``diacc bench --safety``: what PSAR and the
    simulators make of a policy that knows nothing about traffic.
    """

    def __init__(self, name: str) -> None:
        script = name.removesuffix("-nopsar")
        if script not in SCRIPTED:
            raise PolicyError(f"unknown scripted policy {name!r}; known: {', '.join(SCRIPTED)}")
        self.label = name
        self.script = script
        self.base = dataclasses.replace(EnvConfig(), use_psar=not name.endswith("-nopsar"))
        self._rng = np.random.default_rng(0)

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        self._rng = np.random.default_rng([int(seed), 0x5C21])

    def act(self, actor_obs: ActorObs, first_step: bool) -> np.ndarray:
        n_cavs = actor_obs.alive.shape[0]
        if self.script == "random":
            return self._rng.integers(0, len(ACTION_NAMES), n_cavs).astype(np.int64)
        return np.full(n_cavs, ACTION_NAMES.index(self.script), np.int64)


class CheckpointPolicy(Policy):
    """A trained actor, greedy or sampling, with PSAR if its variant uses PSAR."""

    def __init__(self, path: str | Path, variant: str | None = None, sampled: bool = False) -> None:
        import torch

        from diacc.algo.checkpoint import load_actor

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
        if cell.n_vehicles > self.base.obs.max_vehicles:
            raise PolicyError(
                f"cell {cell.key} has {cell.n_vehicles} vehicles but checkpoint {self.path} "
                f"observes at most {self.base.obs.max_vehicles}"
            )
        return super().env_config(cell, settings)

    def begin_episode(self, n_cavs: int, seed: int) -> None:
        import torch

        self._hidden = torch.zeros(n_cavs, self.hidden_size)
        self._generator.manual_seed(seed)

    def act(self, actor_obs: ActorObs, first_step: bool) -> np.ndarray:
        import torch

        from diacc.action_mask import masked_logits
        from diacc.models.inputs import to_tensors

        n_cavs = actor_obs.alive.shape[0]
        start = torch.full((n_cavs,), bool(first_step))
        with torch.no_grad():
            obs = to_tensors(actor_obs)
            logits, self._hidden = self.actor(obs, self._hidden, start)
            logits = masked_logits(logits, obs["action_mask"])  # as in training
            if self.sampled:
                probs = torch.softmax(logits, -1)  # (C, 5)
                action = torch.multinomial(probs, 1, generator=self._generator)[:, 0]
            else:
                action = logits.argmax(-1)
        return action.cpu().numpy().astype(np.int64)  # (C,)

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
    if name in BASELINES or PolicySpec(name).is_scripted:
        if variant is not None:
            raise PolicyError(f"--variant applies to checkpoints, not to the {name} baseline")
        if sampled:
            raise PolicyError(f"--actions sampled applies to checkpoints, not to {name}")
        return PolicySpec(name)
    path = Path(name)
    if path.is_dir():
        if not (path / "checkpoint.pt").exists():
            raise PolicyError(f"run directory {path} has no checkpoint.pt")
        path = path / "checkpoint.pt"
    if path.suffix != ".pt" and not path.exists():
        raise PolicyError(
            f"unknown policy {name!r}; use {', '.join(BASELINES + SCRIPTED)} (scripted ones also "
            "as <name>-nopsar) or the path of a checkpoint.pt"
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
    if spec.is_scripted:
        return ScriptedPolicy(spec.name)
    return CheckpointPolicy(spec.name, spec.variant, spec.sampled)

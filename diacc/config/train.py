"""The trainer's settings: :class:`TrainConfig` (the PPO settings, the run's
variant and directory, the :class:`~diacc.config.env.EnvConfig` it trains in), the
networks' sizes (:class:`ModelConfig`) and the variants of the paper's ablation."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from diacc.config.env import EnvConfig
from diacc.config.mix import MixConfig
from diacc.fields import (
    MAX_ENVS,
    MAX_EPISODE_STEPS,
    MAX_EPOCHS,
    MAX_HEADS,
    MAX_NETWORK_DIM,
    ConfigError,
    check_fields,
    one_of,
    ranged,
)
from diacc.sim.maps import map_tag

_DIM_WHY = "16x the paper's largest, 256; wider networks' updates take hours"
_HEADS_WHY = "each head is a full attention map"


@dataclass(frozen=True)
class ModelConfig:
    """Network sizes of actor and critic.

    The hidden sizes default to 64, the small end of the paper's "of the order
    64-256", with 4 minibatches (:class:`TrainConfig`): the learner that learned at
    least as fast per environment step as the paper's size for less update time
    (the comparison: docs/benchmarks/index.md); every committed trained agent
    uses it. The paper's size is ``configs/paper-learner.toml``
    (:data:`PAPER_LEARNER`). A checkpoint keeps the sizes it was trained with.
    """

    hidden_dim: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    gat_heads: int = ranged(4, 1, MAX_HEADS, why=_HEADS_WHY)
    cross_heads: int = ranged(8, 1, MAX_HEADS, why=_HEADS_WHY)
    cross_dim: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    gru_hidden: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    leaky_slope: float = ranged(0.2, 0)
    taie_concat_heads: bool = False  # TAIE GAT heads hidden/heads wide, concatenated (cheaper)
    # LayerNorm on every GRU's input, actor and critic (diacc.learn.models.recurrent;
    # what it was measured to do: docs/guide/reproducing.md#what-a-collapsed-actor-computes)
    gru_input_norm: bool = False

    def __post_init__(self) -> None:
        check_fields(self)


#: The paper-size learner (hidden sizes 128, one minibatch; entropy bonus 0.01: the
#: defaults before the small learner and the lower bonus) as config overrides;
#: ``configs/paper-learner.toml`` holds the same (a test keeps the two equal) and the
#: benchmarks compare against it.
PAPER_LEARNER: dict[str, Any] = {
    "model.hidden_dim": 128,
    "model.gru_hidden": 128,
    "minibatches": 1,
    "entropy_coef": 0.01,
}


@dataclass(frozen=True)
class Variant:
    """One row of the paper's ablation: which actor, which critic, PSAR on or off.

    Networks are named, not imported, so that configs stay free of torch;
    :mod:`diacc.learn.models.registry` maps the names to classes.
    """

    name: str
    actor: str  # "mlp" (plain MAPPO) or "diadm" (TAIE + GRU, the paper's D-IADM)
    critic: str  # "mlp" or "ciec" (ITDR + GRU, the paper's C-IEC)
    psar: bool  # actions pass through PSAR (paper: PSAR is part of D-IADM)


#: The variants, the only place they are defined: the paper's four, and plain MAPPO
#: under PSAR (``mappo-psar``, not in the paper), so that an ablation with PSAR on for
#: every row shows what the D-IADM actor and the C-IEC critic add.
VARIANT_TABLE: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("mappo", actor="mlp", critic="mlp", psar=False),
        Variant("mappo-iadm", actor="diadm", critic="mlp", psar=True),
        Variant("diacc-nopsar", actor="diadm", critic="ciec", psar=False),
        Variant("diacc", actor="diadm", critic="ciec", psar=True),
        Variant("mappo-psar", actor="mlp", critic="mlp", psar=True),
    )
}
VARIANTS = tuple(VARIANT_TABLE)
#: The paper's ablation (Table III): what ``diacc reproduce`` trains by default.
PAPER_VARIANTS = ("mappo", "mappo-iadm", "diacc-nopsar", "diacc")
#: How a checkpoint picks its evaluation actions: argmax, or drawn from its
#: distribution with a generator seeded by the episode (``--actions``).
ACTION_MODES = ("greedy", "sampled")


@dataclass(frozen=True)
class TrainConfig:
    """One training run: the variant, the PPO settings and the environment it trains in."""

    variant: str = one_of("diacc", VARIANTS)
    total_steps: int = ranged(3_000_000, 1)  # environment steps (decisions x envs)
    n_envs: int = ranged(20, 1, MAX_ENVS, why="each env adds a simulator and rollout rows")
    # sync (in process), batched (one highway simulator for all envs), process (one worker
    # process per core), auto (by backend: batched for highway, process for sumo; process
    # when the learner is on cuda: diacc.envs.vector.auto_vector_mode)
    vector: str = one_of("auto", ("auto", "sync", "batched", "process"))
    rollout_steps: int = ranged(
        100, 1, MAX_EPISODE_STEPS, why="the rollout holds this many steps of every env"
    )
    seed: int = ranged(1, 0, 2**32 - 1)
    # of the PPO update; rollout forwards always run on the CPU
    device: str = one_of("auto", ("auto", "cpu", "cuda"))
    # intra-op threads of the trainer; 0 = diacc.threads rule
    torch_threads: int = ranged(0, 0, 1024, why="more threads than cores only contend")
    update_bf16: bool = False  # bf16 autocast in the PPO update (changes numerics: option)
    # torch.compile the networks' sequence replay in the update (on the static path its
    # whole minibatch loss, as CUDA graphs on cuda)
    update_compile: bool = False
    # eager (whole minibatches, checks per step), static (padded minibatches of one size,
    # no host sync until the update's end: diacc.learn.static_update) or auto (static on
    # cuda, eager on the CPU); the same loss either way
    update_path: str = one_of("auto", ("auto", "eager", "static"))
    # collect the next rollout while the learner trains (second thread): one-update policy lag
    overlap: bool = False
    lr: float = ranged(5e-4, 0, open_low=True)
    adam_eps: float = ranged(1e-5, 0, open_low=True)
    lr_decay: bool = True
    gamma: float = ranged(0.99, 0, 1)
    gae_lambda: float = ranged(0.95, 0, 1)
    clip: float = ranged(0.2, 0, open_low=True)
    epochs: int = ranged(5, 1, MAX_EPOCHS, why="each epoch replays the whole rollout")
    # of whole (chunk, env) sequences per epoch: 4 gives 20 Adam steps per update instead
    # of 5 at the same compute (ModelConfig: measured with hidden 64); needs
    # n_envs x rollout_steps / chunk_len >= minibatches (validate)
    minibatches: int = ranged(4, 1)
    # a tenth of the paper's 0.01 (kept by PAPER_LEARNER): with 0.01 sampled actions lost
    # to the heuristic (docs/results/learning-evidence.md, "Entropy bonus")
    entropy_coef: float = ranged(0.001, 0)
    value_coef: float = ranged(1.0, 0)
    huber_delta: float = ranged(10.0, 0, open_low=True)
    max_grad_norm: float = ranged(10.0, 0, open_low=True)
    chunk_len: int = ranged(10, 1)
    checkpoint_every: int = ranged(10, 1)  # updates
    # "team": one value per env, all CAVs share the advantage (paper); "per_agent":
    # a value per CAV slot from its own features beside the global state (docs)
    critic_values: str = one_of("team", ("team", "per_agent"))
    # "team": every CAV learns from the team reward R (paper); "own": each CAV from its own
    # reward (diacc.envs.reward.own_reward) and its own trip's end (a crash or an arrival
    # ends that CAV's returns); needs critic_values="per_agent" (validate)
    credit: str = one_of("team", ("team", "own"))
    # maps trained on beside env.map: the envs are split into one near-equal share per
    # listed map (diacc.envs.vector.maps_of_envs), so one policy learns several road
    # layouts (--set extra_maps=train-25,right-50.toml); a map listed again gets another
    # share (extra_maps=train-50,train-25 with env.map train-50: 2/3 of the envs on it);
    # () trains on env.map alone
    extra_maps: tuple[str, ...] = ()
    # a distribution of maps and traffic each block of envs draws its cell from, anew
    # every mix.redraw_every updates (diacc.config.mix); off unless it names a map
    mix: MixConfig = field(default_factory=MixConfig)
    # a checkpoint whose networks and value normaliser start this run (fine-tuning, e.g. a
    # highway-trained agent on SUMO: --init-from); the optimiser, the step count and the
    # lr and tau schedules start afresh. "" trains from random weights.
    init_from: str = ""
    # "" (unset): runs/<variant>-<backend>-<map>-s<seed> of this config (default_run_dir);
    # diacc.config.override derives it again when those change and it was not set
    run_dir: str = ""
    env: EnvConfig = field(default_factory=EnvConfig)
    model: ModelConfig = field(default_factory=ModelConfig)

    def __post_init__(self) -> None:
        check_fields(self)
        # The variant decides PSAR: an unset env.use_psar is derived from it, a given
        # one that contradicts it is refused (never overwritten).
        use_psar = VARIANT_TABLE[self.variant].psar
        if self.env.use_psar is None:
            object.__setattr__(self, "env", dataclasses.replace(self.env, use_psar=use_psar))
        elif self.env.use_psar != use_psar:
            wanted = self.env.use_psar
            others = [v.name for v in VARIANT_TABLE.values() if v.psar == wanted]
            raise ConfigError(
                f"env.use_psar={str(wanted).lower()} contradicts variant {self.variant!r}, "
                f"which {'uses' if use_psar else 'does not use'} PSAR; the variant "
                f"decides it: choose one {'with' if wanted else 'without'} PSAR "
                f"({', '.join(others)})"
            )
        # A mix's left-out dimensions are the run's own cell's (MixConfig.following).
        mix = self.mix.following(self.env.scenario, self.env.sim.style_preset, self.env.backend)
        if mix != self.mix:
            object.__setattr__(self, "mix", mix)
        if not self.run_dir:
            object.__setattr__(self, "run_dir", default_run_dir(self))


def default_run_dir(cfg: TrainConfig) -> str:
    """``runs/<variant>-<backend>-<map>-s<seed>``: where a run goes that names no
    directory (the one rule: ``TrainConfig.run_dir`` left empty takes it)."""
    return f"runs/{cfg.variant}-{cfg.env.backend}-{map_tag(cfg.env.map)}-s{cfg.seed}"

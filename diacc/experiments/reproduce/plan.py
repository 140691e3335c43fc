"""What ``diacc reproduce`` will do: budgets, the resolved configuration, runs, jobs, cells.

Everything here is decided before any work starts, so the plan can be
printed (and checked for bad input) first. Two rules shape it:

* **Which checkpoint plays which cell.** A checkpoint is evaluated on the
  cells whose map has the same lane reduction as the map it was trained on
  (25 % or 50 %), as in the paper, where each reduction has its own model;
  cells of a reduction that no training map has are left out of the plan.
* **Budgets.** A preset fixes steps, seeds, environments, episodes, training
  maps, how many zero-shot cells per test map, and the transfer experiment
  together; any explicit option replaces that one value.

The run and result names are the output layout of the command:
``runs/<variant>-<map>-s<seed>[-<backend>]`` (the suffix for runs not trained
on ``highway``) and ``eval/<backend>/<policy>/``.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path

from diacc.config import (
    ACTION_MODES,
    BACKENDS,
    PAPER_VARIANTS,
    STYLE_PRESETS,
    VARIANTS,
    ConfigError,
    SimConfig,
    TrainConfig,
    build_train_config,
    override,
)
from diacc.experiments.grid import DEFAULT_STREAM, GRID_NAMES, Cell, load_grid
from diacc.experiments.policies import BASELINES
from diacc.experiments.sweepaxes import Setting
from diacc.sim.maps import load_map, map_tag

#: Non-learning columns of every table: the :data:`diacc.experiments.policies.BASELINES` (pure
#: HDV, the same vehicles with human drivers in the CAV slots, what a CAV policy's
#: control is measured against, and cooperative CAVs) and the scripted heuristic
#: under PSAR.
BASELINE_COLUMNS = (*BASELINES, "heuristic")
#: Sim-to-sim transfer: this variant, trained on the training backend and on this one.
TRANSFER_VARIANT = "diacc"
TRANSFER_BACKEND = "sumo"
#: The backend whose runs carry no ``-<backend>`` suffix in their names.
DEFAULT_TRAIN_BACKEND = "highway"
DEFAULT_OUT_DIR = Path("results/reproduce")
#: Grids evaluated unless ``--grids`` says otherwise: the paper's training cells
#: (Table II) and its zero-shot rows (Table III); ``zero-shot-product`` on request.
DEFAULT_GRIDS = ("train", "zero-shot")


@dataclass(frozen=True)
class Budget:
    """How big the whole experiment is; one named preset or a preset with overrides."""

    name: str
    steps_per_run: int  # environment steps (decisions x environments) per training run
    seeds: tuple[int, ...]  # run seeds, one training run each per variant and map
    n_envs: int  # environments stepped in parallel by each run
    episodes_per_cell: int  # seeded evaluation episodes per grid cell
    maps: tuple[str, ...]  # training maps
    zero_shot_cells_per_map: int | None  # zero-shot cells kept per test map; None: all
    transfer: bool  # also train diacc on sumo and compare on sumo


#: ``tiny``: the whole pipeline on one map in a few minutes (CI); every number it
#: prints is untrained noise. ``small``: the learning check's 50k steps
#: (docs/results/safety.md), enough for safe but not yet fast agents. ``paper``:
#: the paper's 3 M steps, 3 seeds and 20 environments; the paper does not say how
#: many evaluation episodes it ran, 10 is ``diacc eval``'s default.
BUDGETS: dict[str, Budget] = {
    "tiny": Budget("tiny", 200, (1,), 1, 1, ("train-50",), 1, True),
    "small": Budget("small", 50_000, (1, 2), 4, 2, ("train-25", "train-50"), None, True),
    "paper": Budget("paper", 3_000_000, (1, 2, 3), 20, 10, ("train-25", "train-50"), None, True),
}


#: What each preset is for, shown with its values in ``diacc reproduce --help``.
BUDGET_PURPOSE = {
    "tiny": "the whole pipeline in a few minutes (CI); its numbers are untrained noise",
    "small": "the learning check's 50k steps (there: diacc safe, not yet faster "
    "than human traffic); hours",
    "paper": "the paper's budget; 8-12 h per training run on 2 cores with the paper-size "
    "learner (docs/benchmarks, Measured figures; the default small one is cheaper), so days",
}


def describe_budget(budget: Budget) -> str:
    """One line of a budget's values, e.g. for ``--help``."""
    from diacc.console import plural

    zero_shot = (
        "all zero-shot cells"
        if budget.zero_shot_cells_per_map is None
        else f"{plural(budget.zero_shot_cells_per_map, 'zero-shot cell')} per test map"
    )
    return (
        f"{budget.steps_per_run:,} steps per run, {plural(budget.n_envs, 'env')}, seeds "
        f"{','.join(map(str, budget.seeds))}, maps {','.join(budget.maps)}, "
        f"{plural(budget.episodes_per_cell, 'episode')} per cell, {zero_shot}, "
        f"transfer {'on' if budget.transfer else 'off'}"
    )


@dataclass(frozen=True)
class ReproduceConfig:
    """Everything that decides the results of ``diacc reproduce`` (not how it is executed)."""

    budget: Budget
    out_dir: Path = DEFAULT_OUT_DIR
    variants: tuple[str, ...] = PAPER_VARIANTS
    backends: tuple[str, ...] = BACKENDS  # evaluated on
    train_backend: str = DEFAULT_TRAIN_BACKEND
    grids: tuple[str, ...] = DEFAULT_GRIDS
    style_preset: str = SimConfig.style_preset  # HDV styles, training and evaluation
    episode_steps: int | None = None  # evaluation episode length; None: the policy's own
    actions: str = "greedy"  # checkpoints' evaluation actions: argmax, or "sampled" (seeded)
    # evaluation seed stream: "test" to report, "validation" where a sweep chooses a setting
    stream: str = DEFAULT_STREAM
    device: str = TrainConfig.device  # torch device of the PPO updates (as 'diacc train')
    train_sets: tuple[str, ...] = ()  # KEY=VALUE training overrides, as `diacc train --set`
    # config settings each variant is trained with (--sweep/--study); () = one, the defaults
    settings: tuple[Setting, ...] = ()


@dataclass(frozen=True)
class Execution:
    """How the work is spread; changes no result."""

    jobs: int = 1  # local training processes and evaluation workers
    engine: str = "local"  # or "ray"
    ray_address: str | None = None
    ray_cpus: int | None = None
    cpus_per_run: float = 1.0  # CPUs Ray reserves per training run
    progress: bool = True  # progress bars (the [k/n] lines are always printed)


@dataclass(frozen=True)
class RunSpec:
    """One training run."""

    variant: str
    map: str
    seed: int
    backend: str
    setting: Setting = Setting()  # --sweep values; its name ends the run name

    @property
    def name(self) -> str:
        suffix = "" if self.backend == DEFAULT_TRAIN_BACKEND else f"-{self.backend}"
        setting = f"-{self.setting.name}" if self.setting.values else ""
        return f"{self.variant}-{map_tag(self.map)}-s{self.seed}{suffix}{setting}"

    @property
    def column(self) -> str:
        """Its table column and figure label: the variant, with the setting if any."""
        return f"{self.variant} {self.setting.label}" if self.setting.values else self.variant


@dataclass(frozen=True)
class EvalJob:
    """One policy on one backend: one ``diacc eval`` results directory."""

    backend: str
    policy: str  # a baseline name or a run name
    run: RunSpec | None  # None for baselines
    cells: tuple[Cell, ...]

    @property
    def rel_dir(self) -> Path:
        return Path("eval") / self.backend / self.policy


@dataclass(frozen=True)
class Plan:
    """The resolved work of one ``diacc reproduce`` invocation."""

    config: ReproduceConfig
    runs: tuple[RunSpec, ...]
    grid_cells: dict[str, tuple[Cell, ...]]  # grid name -> cells evaluated
    jobs: tuple[EvalJob, ...]
    transfer_pairs: tuple[tuple[RunSpec, RunSpec], ...]  # (training backend, sumo) runs
    transfer_cells: tuple[Cell, ...]
    notes: tuple[str, ...]  # decisions the user should see (e.g. why transfer is off)

    def run_dir(self, run: RunSpec) -> Path:
        return self.config.out_dir / "runs" / run.name

    def eval_dir(self, job: EvalJob) -> Path:
        return self.config.out_dir / job.rel_dir

    def train_config(self, run: RunSpec) -> TrainConfig:
        """The full training config of a run: defaults, budget, preset, --set, the run, then
        its --sweep setting."""
        cfg = self.config
        trained = build_train_config(
            variant=run.variant,
            backend=run.backend,
            map=run.map,
            steps=cfg.budget.steps_per_run,
            envs=cfg.budget.n_envs,
            seed=run.seed,
            device=cfg.device,
            run_dir=self.run_dir(run),
            style_preset=cfg.style_preset,
            sets=cfg.train_sets,
        )
        return override(trained, run.setting.changes)

    def planned_steps(self, run: RunSpec) -> int:
        """Environment steps the run will have taken when done (whole updates)."""
        from diacc.experiments.scaleout import planned_steps

        return planned_steps(self.train_config(run))


# ----------------------------------------------------------------------------- resolution
def resolve_config(
    budget: str,
    *,
    steps: int | None = None,
    seeds: tuple[int, ...] | None = None,
    envs: int | None = None,
    episodes: int | None = None,
    maps: tuple[str, ...] | None = None,
    zero_shot_cells: int | None = None,
    transfer: bool | None = None,
    **fields,
) -> tuple[ReproduceConfig, tuple[str, ...]]:
    """(config, notes): ``budget``'s preset with every option given (not None) replacing its value.

    ``zero_shot_cells`` 0 means all cells. ``fields`` are :class:`ReproduceConfig`
    fields. Bad values raise :class:`ConfigError` with a one-line message.
    """
    if budget not in BUDGETS:
        raise ConfigError(f"unknown budget {budget!r}; use one of {', '.join(BUDGETS)}")
    preset = BUDGETS[budget]
    changes = {
        "steps_per_run": steps,
        "seeds": seeds,
        "n_envs": envs,
        "episodes_per_cell": episodes,
        "maps": maps,
        "transfer": transfer,
    }
    changes = {k: v for k, v in changes.items() if v is not None}
    if zero_shot_cells is not None:
        changes["zero_shot_cells_per_map"] = zero_shot_cells or None
    notes = []
    train_backend = fields.get("train_backend", DEFAULT_TRAIN_BACKEND)
    if train_backend == TRANSFER_BACKEND and changes.get("transfer", preset.transfer):
        if transfer:
            raise ConfigError(
                f"--transfer compares a policy trained on another backend with one trained on "
                f"{TRANSFER_BACKEND}; it needs --train-backend {DEFAULT_TRAIN_BACKEND}"
            )
        changes["transfer"] = False
        notes.append(f"transfer: off (the training backend is {TRANSFER_BACKEND} already)")
    name = preset.name if not changes else f"{preset.name} (with overrides)"
    config = ReproduceConfig(budget=dataclasses.replace(preset, name=name, **changes), **fields)
    check_config(config)
    return config, tuple(notes)


def _unknown(kind: str, values, known) -> None:
    bad = [v for v in values if v not in known]
    if bad:
        raise ConfigError(f"unknown {kind} {bad[0]!r}; use some of {', '.join(known)}")


def check_config(config: ReproduceConfig) -> None:
    """One-line :class:`ConfigError` for the first bad value of a config."""
    b = config.budget
    for label, value in (
        ("--steps", b.steps_per_run),
        ("--envs", b.n_envs),
        ("--episodes", b.episodes_per_cell),
    ):
        if value < 1:
            raise ConfigError(f"{label} must be >= 1, got {value}")
    if b.zero_shot_cells_per_map is not None and b.zero_shot_cells_per_map < 0:
        raise ConfigError(f"--zero-shot-cells must be >= 0, got {b.zero_shot_cells_per_map}")
    if config.episode_steps is not None and config.episode_steps < 1:
        raise ConfigError(f"--episode-steps must be >= 1, got {config.episode_steps}")
    for label, values in (
        ("--seeds", b.seeds),
        ("--maps", b.maps),
        ("--variants", config.variants),
        ("--backends", config.backends),
        ("--grids", config.grids),
    ):
        if not values:
            raise ConfigError(f"{label} must name at least one value")
        if len(set(values)) < len(values):
            raise ConfigError(f"{label} names a value twice: {', '.join(map(str, values))}")
    _unknown("variant", config.variants, VARIANTS)
    _unknown("backend", config.backends, BACKENDS)
    _unknown("training backend", (config.train_backend,), BACKENDS)
    _unknown("grid", config.grids, GRID_NAMES)
    _unknown("style preset", (config.style_preset,), tuple(STYLE_PRESETS))
    _unknown("--actions", (config.actions,), ACTION_MODES)
    for map_name in b.maps:
        load_map(map_name)  # one-line MapError for an unknown map


# ----------------------------------------------------------------------------- cells
@functools.cache
def reduction_of(map_name: str) -> tuple[str, ...]:
    """The lane-reduction segment kinds of a map, e.g. ``("reduction50",)``."""
    return tuple(sorted({s.kind for s in load_map(map_name).segments} - {"multilane"}))


def _spread(cells: list[Cell], keep: int | None) -> list[Cell]:
    """``keep`` cells of each map, evenly spaced in grid order (all if None)."""
    if keep is None:
        return cells
    out = []
    for map_name in dict.fromkeys(c.map for c in cells):
        mine = [c for c in cells if c.map == map_name]
        picks = sorted({int(i * len(mine) / keep) for i in range(min(keep, len(mine)))})
        out += [mine[i] for i in picks]
    return out


def grid_cells(grid: str, maps: tuple[str, ...], keep_per_map: int | None = None) -> list[Cell]:
    """Cells of a named grid that share a lane reduction with one of the training maps."""
    reductions = {reduction_of(m) for m in maps}
    cells = [c for c in load_grid(grid) if reduction_of(c.map) in reductions]
    return _spread(cells, keep_per_map)


def make_plan(config: ReproduceConfig, notes: tuple[str, ...] = ()) -> Plan:
    """Runs, evaluation jobs and cells of a config (see the module docstring)."""
    b = config.budget
    # Seed-major: an interrupted reproduction has every variant and setting of the
    # first seed before it starts the second, so a partial one already compares them.
    runs = [
        RunSpec(v, m, s, config.train_backend, setting)
        for s in b.seeds
        for m in b.maps
        for setting in config.settings or (Setting(),)
        for v in config.variants
    ]
    pairs = []
    if b.transfer and config.settings:
        notes = (*notes, "transfer: off (a --sweep/--study reproduction compares settings)")
    elif b.transfer:
        for m in b.maps:
            for s in b.seeds:
                pairs.append(
                    (
                        RunSpec(TRANSFER_VARIANT, m, s, config.train_backend),
                        RunSpec(TRANSFER_VARIANT, m, s, TRANSFER_BACKEND),
                    )
                )
        runs += [r for pair in pairs for r in pair]
    runs = list(dict.fromkeys(runs))
    cells_of = {
        g: tuple(grid_cells(g, b.maps, b.zero_shot_cells_per_map if g != "train" else None))
        for g in config.grids
    }
    for grid, cells in cells_of.items():
        if not cells:
            raise ConfigError(f"grid {grid!r} has no cell with the lane reduction of {b.maps[0]}")
    all_cells = list(dict.fromkeys(c for cells in cells_of.values() for c in cells))
    transfer_cells = tuple(grid_cells("train", b.maps)) if pairs else ()

    jobs: dict[tuple[str, str], EvalJob] = {}

    def add(backend: str, policy: str, run: RunSpec | None, cells) -> None:
        if run is not None:
            cells = [c for c in cells if reduction_of(c.map) == reduction_of(run.map)]
        old = jobs.get((backend, policy))
        merged = tuple(dict.fromkeys([*(old.cells if old else ()), *cells]))
        if merged:
            jobs[(backend, policy)] = EvalJob(backend, policy, run, merged)

    main_runs = [
        r for r in runs if r.variant in config.variants and r.backend == config.train_backend
    ]
    for backend in config.backends:
        for policy in BASELINE_COLUMNS:
            add(backend, policy, None, all_cells)
        for run in main_runs:
            add(backend, run.name, run, all_cells)
    if pairs:
        add(TRANSFER_BACKEND, "pure-hdv", None, transfer_cells)
        for pair in pairs:
            for run in pair:
                add(TRANSFER_BACKEND, run.name, run, transfer_cells)
    return Plan(
        config, tuple(runs), cells_of, tuple(jobs.values()), tuple(pairs), transfer_cells, notes
    )


def describe_plan(plan: Plan) -> list[str]:
    """The lines ``diacc reproduce`` prints before it starts: what, how much, where."""
    from diacc.console import plural

    cfg, b = plan.config, plan.config.budget
    n_settings = max(len(cfg.settings), 1)
    main = len(cfg.variants) * len(b.maps) * n_settings * len(b.seeds)
    extra = len(plan.runs) - main
    steps = sum(plan.planned_steps(r) for r in plan.runs)
    episodes = sum(len(j.cells) for j in plan.jobs) * b.episodes_per_cell
    episode_steps = cfg.episode_steps or SimConfig.episode_steps
    cells = ", ".join(f"{g} {len(c)}" for g, c in plan.grid_cells.items())
    if plan.transfer_pairs:
        cells += f" (+ transfer {len(plan.transfer_cells)} on {TRANSFER_BACKEND})"
    lines = [
        f"diacc reproduce: budget {b.name}, results in {cfg.out_dir}",
        f"  training: {plural(len(plan.runs), 'run')} = {plural(len(cfg.variants), 'variant')} "
        f"x {plural(len(b.maps), 'map')} "
        + (f"x {plural(n_settings, 'setting')} " if cfg.settings else "")
        + f"x {plural(len(b.seeds), 'seed')} on {cfg.train_backend}"
        + (f" + {extra} for the transfer" if extra else "")
        + f"; {b.steps_per_run:,} env steps each with {plural(b.n_envs, 'env')}; "
        f"{steps:,} env steps in all",
        f"    variants {', '.join(cfg.variants)}; maps {', '.join(b.maps)}; "
        f"seeds {', '.join(map(str, b.seeds))}",
        f"  evaluation: {len(plan.jobs)} jobs (policy x backend) on {', '.join(cfg.backends)}; "
        f"cells: {cells}; {plural(b.episodes_per_cell, 'episode')} per cell: "
        f"{episodes:,} episodes in all (at most {episodes * episode_steps:,} "
        "decision steps)",
        f"  HDV style preset {cfg.style_preset}; evaluation episodes of "
        + (f"{cfg.episode_steps} steps" if cfg.episode_steps else "the policy's own length")
        + f"; checkpoints act {cfg.actions}; transfer {'on' if plan.transfer_pairs else 'off'}; "
        f"seed stream {cfg.stream}",
    ]
    for grid in cfg.grids:
        if b.zero_shot_cells_per_map is not None and grid != "train":
            per_map = len(load_grid(grid)) // 2
            lines.append(
                f"  {grid} grid: {b.zero_shot_cells_per_map} of {per_map} cells per test map "
                "(--zero-shot-cells 0 for all)"
            )
    lines += [f"  setting {s.label}" for s in cfg.settings]
    lines += [f"  {note}" for note in plan.notes]
    return lines

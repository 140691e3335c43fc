"""Run control of ``diacc train``: everything around the PPO of :mod:`diacc.learn.ppo`.

:func:`train` checks the config, claims and locks the run directory, builds
the agent (or restores it from the checkpoint with ``--resume``) and runs the
updates: lr decay, the reward's softmin temperature at the run's global step
(:func:`~diacc.learn.ppo.collect_rollout` sets it in the envs), one rollout and one
:func:`~diacc.learn.ppo.learn` per update, a ``progress.jsonl`` row and
TensorBoard scalars per update (:mod:`diacc.learn.progress`), checkpoints,
and a stop at the next update boundary on SIGINT/SIGTERM/SIGHUP.

* Every update starts all environments afresh with seeds derived from
  (run seed, env, update); with the RNG states in the checkpoint this makes
  ``--resume`` reproduce an uninterrupted run exactly.
* **Overlap** (``overlap = true``, off by default): the next rollout is
  collected on the main thread while a second thread runs the PPO update,
  so both cores work. That rollout acts with the parameters from *before*
  the update (a one-update policy lag); PPO's ratios are taken against the
  stored log-probabilities of that behaviour policy, so its importance
  weighting and clipping apply as they are (:func:`~diacc.learn.ppo.add_proximal_policy`).
  See :func:`_learn_beside_rollout`.
"""

from __future__ import annotations

import functools
import json
import random
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

from diacc.config import TrainConfig, flatten_config, resolve_road, train_slots, validate
from diacc.config.mix import corner_scenarios
from diacc.console import TrainProgress
from diacc.envs.actions import ACTION_NAMES
from diacc.envs.mix import Cell, cells_of_envs, describe, draw_cells, redraw_index
from diacc.envs.observation import check_road
from diacc.envs.vector import TrainingEnvs, make_vector_env
from diacc.errors import DiaccError
from diacc.fileio import atomic_write, check_output_dir
from diacc.learn.agent import Agent, make_agent
from diacc.learn.checkpoint import (
    CheckpointError,
    config_from_checkpoint,
    init_networks,
    load_checkpoint,
    restore,
    save_checkpoint,
    set_rng_state,
)
from diacc.learn.collapse import COLLAPSE_SHARE, collapse_warning, top_action_share
from diacc.learn.ppo import NonFiniteError, collect_rollout, learn
from diacc.learn.progress import UpdateStats, progress_record, write_record
from diacc.learn.progress import check_agrees as check_progress
from diacc.learn.progress import keep_until as keep_progress_until
from diacc.learn.progress import read_rows as progress_rows
from diacc.runlog import claim_run_dir, config_digest, locked_dir, log, run_log
from diacc.sim.scenario import draw_population
from diacc.threads import set_torch_threads


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TrainingError(
            "--device cuda requested but this machine has no CUDA device "
            f"(torch {torch.__version__}); use --device cpu or auto"
        )
    return torch.device(name)


def device_here(name: str) -> str:
    """The device ``name`` means on this machine (``auto`` -> ``cuda`` or ``cpu``), without
    :func:`resolve_device`'s check: a resume compares what the update ran on, so that a
    run saved with ``device`` ``cpu`` continues under ``auto`` on a machine without CUDA
    (the default of ``sweep`` and ``reproduce`` was ``cpu`` before it became ``auto``)."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


# ----------------------------------------------------------------------------- training
class TrainingError(DiaccError, RuntimeError):
    """Training cannot go on (a non-finite update, a missing device); the message is one line."""


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT/SIGTERM stopped the run at an update boundary, after saving a checkpoint."""

    def __init__(self, signum: int, update: int, checkpoint: Path) -> None:
        self.signum, self.update, self.checkpoint = signum, update, checkpoint
        super().__init__(
            f"interrupted by {signal.Signals(signum).name} after update {update}; "
            f"checkpoint saved to {checkpoint} (continue with --resume)"
        )


#: Config fields a resumed run may change: the step budget, and where the run lives.
RESUME_FREE_FIELDS = ("total_steps", "run_dir")


def check_resume_config(
    saved: dict, cfg: TrainConfig, path: Path, allow_change: bool = False
) -> list[str]:
    """Fields (other than :data:`RESUME_FREE_FIELDS`) where ``cfg`` differs from the checkpoint's.

    ``device`` counts as what it means here (:func:`device_here`). Raises
    :class:`CheckpointError` naming the first one unless ``allow_change``.
    """
    old, new = flatten_config(saved), flatten_config(asdict(cfg))
    for flat in (old, new):
        if "device" in flat:
            flat["device"] = device_here(flat["device"])
    changed = [
        k
        for k in sorted(set(old) | set(new), key=lambda k: (k.count("."), k))  # top level first
        if k not in RESUME_FREE_FIELDS and old.get(k) != new.get(k)
    ]
    if changed and not allow_change:
        key = changed[0]
        raise CheckpointError(
            f"checkpoint {path} was trained with {key} {old.get(key)!r}, not {new.get(key)!r}; "
            "--resume may change only --steps (pass --allow-config-change to override)"
        )
    return changed


class StoppedAtOnce(KeyboardInterrupt):
    """A second SIGINT/SIGTERM: training stopped mid-update; ``signum`` sets the exit status."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    def __str__(self) -> str:
        return f"stopped at once by a second {signal.Signals(self.signum).name}"


def _check_collapse(greedy: np.ndarray, first: int, last: int) -> None:
    """Log the collapse check of updates ``first``-``last`` (their greedy action counts,
    :mod:`diacc.learn.collapse`): a warning for a collapsed policy, else one info line."""
    where = f"in updates {first}-{last} of training"
    warning = collapse_warning("the actor's greedy policy", greedy, where)
    if warning is not None:
        log.warning("%s", warning)
        return
    top, share = top_action_share(greedy)
    log.info(
        "collapse check, updates %d-%d: greedy %r on %.1f%% of %d decisions (collapsed: >= %.0f%%)",
        first,
        last,
        ACTION_NAMES[top],
        100.0 * share,
        int(greedy.sum()),
        100.0 * COLLAPSE_SHARE,
    )


class _StopOnSignal:
    """SIGINT/SIGTERM/SIGHUP set :attr:`signum`; the loop stops at the next update boundary.

    A second signal stops at once (:class:`StoppedAtOnce`), keeping the last checkpoint.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.signum: int | None = None
        self.previous: dict = {}

    def __enter__(self) -> _StopOnSignal:
        if threading.current_thread() is threading.main_thread():
            self.previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)

    def _handle(self, signum: int, frame) -> None:
        if self.signum is not None:
            raise StoppedAtOnce(signum)
        self.signum = signum
        log.warning(
            "%s received: saving a checkpoint after the current update (again to stop now)",
            signal.Signals(signum).name,
        )


def check_config(cfg: TrainConfig) -> None:
    """One-line errors for a config :func:`train` cannot run, before anything is printed or written.

    The first vehicles' placement checks that the scenario fits the map (it used
    to fail in the first reset, after config.json and tb/ existed), on the road the
    environments will drive (:func:`~diacc.config.resolve_road`).
    """
    validate(cfg)
    for road_map in (cfg.env.map, *cfg.extra_maps):
        road = resolve_road(replace(cfg.env, map=road_map))
        check_road(road)  # the observation's road and lane tables hold it
        draw_population(cfg.env.scenario, road, cfg.seed)
    if cfg.mix.on:  # every map of the mix, with the most vehicles a cell has
        largest = max(corner_scenarios(cfg.mix, cfg.env.scenario), key=lambda s: s.n_vehicles)
        for road_map in dict.fromkeys(cfg.mix.map_names()):
            road = resolve_road(replace(cfg.env, map=road_map))
            check_road(road)
            draw_population(largest, road, cfg.seed)


def train(
    cfg: TrainConfig,
    resume: bool = False,
    progress: bool = True,
    stop_after_updates: int | None = None,
    allow_config_change: bool = False,
    overwrite: bool = False,
    stop_at_step: int | None = None,
) -> Path:
    """Train ``cfg.variant``; returns the run directory (config, checkpoints, logs).

    ``stop_after_updates`` ends the run early (as if interrupted) after that
    many updates, with a checkpoint, and so does ``stop_at_step`` at the first
    update boundary at or past that env step of the schedule (a long run in
    pieces, or a study that compares runs at equal steps of one schedule: tau
    and lr follow ``total_steps``); ``resume=True`` continues from it, with
    the same config but for the step budget (unless ``allow_config_change``),
    and cuts ``progress.jsonl`` and TensorBoard back to the checkpoint.
    Nothing is written before the config (and checkpoint) passed their checks.
    The run directory is locked while training; one that holds a run is
    refused unless ``resume`` (continue it) or ``overwrite`` (replace it).
    """
    check_config(cfg)
    device = resolve_device(cfg.device)
    run_dir = Path(cfg.run_dir)
    with locked_dir(run_dir, "train"):
        claim_run_dir(run_dir, resume, overwrite)
        # TensorBoard's writer thread would find an unwritable tb/ only after the first update.
        check_output_dir(run_dir / "tb")
        return _start(
            cfg,
            run_dir,
            device,
            resume,
            progress,
            stop_after_updates,
            allow_config_change,
            stop_at_step,
        )


def _start(
    cfg: TrainConfig,
    run_dir: Path,
    device: torch.device,
    resume: bool,
    progress: bool,
    stop_after_updates: int | None,
    allow_config_change: bool,
    stop_at_step: int | None = None,
) -> Path:
    """:func:`train` once the inputs are checked and ``run_dir`` is locked and claimed."""
    ckpt_path = run_dir / "checkpoint.pt"
    seed_everything(cfg.seed)
    set_torch_threads(cfg.torch_threads)
    agent = make_agent(cfg, device)
    steps_per_update = cfg.rollout_steps * cfg.n_envs
    n_updates = max(1, cfg.total_steps // steps_per_update)
    first_update, global_step, changed, rows = 0, 0, [], None
    progress_path = run_dir / "progress.jsonl"
    if resume:
        payload = load_checkpoint(ckpt_path, device)
        saved = asdict(config_from_checkpoint(payload))
        changed = check_resume_config(saved, cfg, ckpt_path, allow_config_change)
        restore(agent, payload, cfg, ckpt_path)
        first_update, global_step = payload["update"], payload["global_step"]
        if progress_path.exists():  # checked before anything is written
            rows = progress_rows(progress_path)
            check_progress(rows, progress_path, first_update, global_step)
        set_rng_state(payload["rng"])
    elif cfg.init_from:
        source = init_networks(agent, Path(cfg.init_from), cfg)
    with run_log(run_dir / "train.log"):
        if cfg.init_from and not resume:
            log.info(
                "networks from %s (%s, trained on %s %s for %d steps); optimiser fresh",
                cfg.init_from,
                source["variant"],
                source["backend"],
                source["map"],
                source["global_step"],
            )
        if changed:
            log.warning("resuming %s with changed config fields: %s", run_dir, ", ".join(changed))
        if rows is not None:
            keep_progress_until(progress_path, rows, first_update)
        atomic_write(run_dir / "config.json", json.dumps(asdict(cfg), indent=2, default=str))
        last_update = (
            n_updates
            if stop_after_updates is None
            else min(n_updates, first_update + stop_after_updates)
        )
        if stop_at_step is not None:
            at_step = -(-stop_at_step // steps_per_update)  # the update that reaches it
            last_update = max(first_update, min(last_update, at_step))
        return _train_loop(
            agent, cfg, run_dir, device, first_update, last_update, n_updates, global_step, progress
        )


def _train_loop(
    agent: Agent,
    cfg: TrainConfig,
    run_dir: Path,
    device: torch.device,
    first_update: int,
    last_update: int,
    n_updates: int,
    global_step: int,
    progress: bool,
) -> Path:
    ckpt_path = run_dir / "checkpoint.pt"
    steps_per_update = cfg.rollout_steps * cfg.n_envs
    saved_update = first_update if first_update else None
    mix = _MixDraws(cfg) if cfg.mix.on else None
    envs = make_vector_env(
        cfg.env,
        cfg.n_envs,
        cfg.seed,
        cfg.vector,
        cfg.extra_maps,
        learner_device=device.type,
        env_cells=None if mix is None else mix.env_cells(first_update),
        n_slots=train_slots(cfg),
    )
    # purge_step: TensorBoard drops the events a resumed run logged after its checkpoint.
    # It reads event files in name order, and names start with the creation second:
    # a resumed file must not share its second with the interrupted run's last file.
    if first_update:
        _wait_past_event_files(run_dir / "tb")
    writer = SummaryWriter(
        str(run_dir / "tb"), purge_step=global_step + 1 if first_update else None
    )
    bar = TrainProgress(n_updates * steps_per_update, global_step, f"train {cfg.variant}", progress)
    log.info(
        "start: %s in %s, updates %d-%d of %d (%d env steps each), config %s",
        cfg.variant,
        run_dir,
        first_update + 1,
        last_update,
        n_updates,
        steps_per_update,
        config_digest(cfg),
    )
    scenario = cfg.env.scenario
    if scenario.n_slots < scenario.n_cavs:  # a cap: say so, the CAVs beyond it are not agents
        log.warning(
            "agent slots capped at %d of the episode's %d CAVs (env.scenario.cav_slots %s): "
            "a CAV that finds every slot taken drives itself; 'every' gives each CAV its own",
            scenario.n_slots,
            scenario.n_cavs,
            scenario.cav_slots,
        )
    started_s = time.perf_counter()
    try:
        with _StopOnSignal() as stop:
            # The next update's rollout when overlap collected it beside the learner
            # (lagged: one update behind), else None.
            collected, lagged = None, False
            greedy = np.zeros(len(ACTION_NAMES), np.int64)  # (A,) since the last checkpoint
            for update in range(first_update, last_update):
                t0 = time.perf_counter()
                if cfg.lr_decay:
                    for group in agent.optimizer.param_groups:
                        group["lr"] = cfg.lr * (1.0 - update / n_updates)
                if mix is not None:
                    mix.set(envs, update)
                if collected is None:
                    collected, lagged = (
                        collect_rollout(agent, envs, cfg, update, global_step, values=False),
                        False,
                    )
                roll, next_value, rollout = collected
                if rollout.restarts:
                    log.warning(
                        "update %d: %d simulator restart(s) in the rollout; episodes cut",
                        update + 1,
                        rollout.restarts,
                    )
                # Prefetch the next rollout during this update, except before a checkpoint:
                # a resumed run then collects it exactly as the uninterrupted one did.
                prefetch = (
                    cfg.overlap
                    and update + 1 < last_update
                    and (update + 1) % cfg.checkpoint_every != 0
                )
                collected = None
                learn_roll = functools.partial(
                    learn,
                    agent,
                    roll,
                    next_value,
                    cfg,
                    device,
                    envs.n_cavs,
                    _update_generator(cfg, update, device),
                    lagged,
                )
                try:
                    if prefetch:
                        returns, losses, collected = _learn_beside_rollout(
                            learn_roll,
                            agent,
                            envs,
                            cfg,
                            update,
                            global_step + steps_per_update,
                            mix,
                        )
                        lagged = True
                    else:
                        returns, losses = learn_roll()
                except NonFiniteError as exc:
                    kept = (
                        f"checkpoint {ckpt_path} still holds update {saved_update}"
                        if saved_update
                        else "no checkpoint was written"
                    )
                    raise TrainingError(
                        f"update {update + 1}: {exc}; training stopped, this update is not "
                        f"saved and {kept}"
                    ) from None
                global_step += steps_per_update
                lr = agent.optimizer.param_groups[0]["lr"]
                stats = UpdateStats(update + 1, global_step, lr, losses, roll, returns, rollout)
                record = progress_record(stats, update_s=time.perf_counter() - t0)
                record["rollout_cpu_s"] = rollout.cpu_seconds
                greedy += rollout.greedy
                write_record(record, writer, run_dir / "progress.jsonl")
                bar.update(steps_per_update, record["team_reward"], rollout.episodes)
                if (
                    (update + 1) % cfg.checkpoint_every == 0
                    or update + 1 == last_update
                    or stop.signum is not None
                ):
                    save_checkpoint(ckpt_path, agent, cfg, update + 1, global_step)
                    log.info("checkpoint: update %d, env step %d", update + 1, global_step)
                    _check_collapse(greedy, (saved_update or 0) + 1, update + 1)
                    saved_update, greedy[:] = update + 1, 0
                if stop.signum is not None and update + 1 < last_update:
                    log.warning("stopped after update %d; checkpoint saved", update + 1)
                    raise TrainingInterrupted(stop.signum, update + 1, ckpt_path)
    finally:
        bar.close()
        writer.close()
        envs.close()
    log.info(
        "end: after update %d of %d, env step %d, %.1f s",
        last_update,
        n_updates,
        global_step,
        time.perf_counter() - started_s,
    )
    return run_dir


def _update_generator(cfg: TrainConfig, update: int, device: torch.device):
    """Minibatch RNG of an update: torch's global one, or with ``overlap`` its own.

    Seeded from (run seed, update), so that overlapped runs are reproducible
    and resume exactly without storing its state.
    """
    if not cfg.overlap:
        return None
    return torch.Generator(device=device).manual_seed(cfg.seed * 1_000_003 + update)


def _learn_beside_rollout(
    learn_roll: Callable[[], tuple[np.ndarray, dict[str, float]]],
    agent: Agent,
    envs: TrainingEnvs,
    cfg: TrainConfig,
    update: int,
    next_step: int,
    mix: _MixDraws | None = None,
):
    """Run ``learn_roll`` (:func:`learn` of this update) on a second thread while
    this one collects update + 1's rollout.

    The rollout networks keep the parameters from before this update (no
    sync until both are done), which is the one-update policy lag. torch
    releases the GIL inside its kernels, so the two threads run on two cores
    for most of the update. Returns (returns, losses, next rollout); an error
    of the update is raised here after both finished.
    """
    result: dict = {}

    def run_update() -> None:
        try:
            result["learnt"] = learn_roll()
        except BaseException as exc:  # re-raised on the main thread
            result["error"] = exc

    learner = threading.Thread(target=run_update, name="diacc-learner")
    learner.start()
    try:
        if mix is not None:
            mix.set(envs, update + 1)
        collected = collect_rollout(
            agent, envs, cfg, update + 1, next_step, sync=False, values=False
        )
    finally:
        learner.join()
    if "error" in result:
        raise result["error"]
    agent.sync_rollout()
    return (*result["learnt"], collected)


class _MixDraws:
    """The training mix's cells of each update (:mod:`diacc.envs.mix`): drawn at each
    redraw from (run seed, redraw, block) alone, so that a resumed run trains on the
    cells an uninterrupted one did; a draw that changes the cells is one line of the
    run log (a one-cell mix draws the same cells every update: one line in all)."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg, self.current = cfg, -1  # the redraw the envs hold

    def env_cells(self, update: int) -> list[Cell]:
        """Each env's cell at ``update`` (logged when it is a new draw)."""
        cfg, redraw = self.cfg, redraw_index(self.cfg.mix, update)
        blocks = draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, redraw)
        if redraw != self.current:
            line = describe(blocks, cfg.n_envs)
            before = draw_cells(cfg.mix, cfg.env.scenario, cfg.seed, redraw - 1) if redraw else []
            if not before or line != describe(before, cfg.n_envs):  # the same on resume
                log.info("update %d: mix draw %d: %s", update + 1, redraw, line)
            self.current = redraw
        return cells_of_envs(blocks, cfg.n_envs)

    def set(self, envs: TrainingEnvs, update: int) -> None:
        """Give ``envs`` the cells of ``update`` if they hold another draw's."""
        if redraw_index(self.cfg.mix, update) != self.current:
            envs.set_cells(self.env_cells(update))


def _wait_past_event_files(tb_dir: Path) -> None:
    """Sleep (at most ~1 s) until the clock's second is past every event file's."""
    stamps = [int(p.name.split(".")[3]) for p in tb_dir.glob("events.out.tfevents.*")]
    while stamps and int(time.time()) <= max(stamps):
        time.sleep(0.05)

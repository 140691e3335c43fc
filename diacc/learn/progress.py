"""``progress.jsonl``: one JSON object per finished update, appended by the trainer.

Read back by ``--resume`` (cut to the checkpoint's update) and by ``diacc plot
curves``; both read it here so that a damaged file (bytes that are not UTF-8,
a row that is not an object, a step counter that is not a whole number, a
value that is not a number) is the same one line naming the file and row,
never a traceback or a curve drawn from strings. A last line without its
newline that does not parse is what a killed trainer leaves mid-write: it is
dropped, not refused.

Written here too: :func:`progress_record` makes an update's row,
:func:`write_record` appends it (and to TensorBoard).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from diacc.envs.psar import RULE_NAMES
from diacc.errors import DiaccError
from diacc.fileio import atomic_write, open_append
from diacc.learn.collapse import top_action_share

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

    from diacc.learn.buffer import Rollout
    from diacc.learn.ppo import RolloutStats

#: The two step counters every row holds.
COUNTERS = ("update", "global_step")


class ProgressError(DiaccError, ValueError):
    """``progress.jsonl`` is damaged, or does not agree with the run's checkpoint."""


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_rows(path: Path) -> list[dict]:
    """The rows of ``path`` (a torn last line dropped); one line if it is damaged."""
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ProgressError(f"{path}:{line} is not UTF-8 text") from None
    lines = text.split("\n")
    rows = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError:
            if number == len(lines):  # no newline after it: a write cut short by a kill
                break
            raise ProgressError(f"{path}:{number} is not valid JSON") from None
        if not isinstance(row, dict):
            raise ProgressError(f"{path}:{number} is not a JSON object")
        for key in COUNTERS:
            value = row.get(key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ProgressError(
                    f"{path}:{number}: {key!r} is not a whole number >= 0 ({value!r:.40})"
                )
        for key, value in row.items():
            if not (_is_number(value) or value is None):
                raise ProgressError(f"{path}:{number}: {key!r} is not a number ({value!r:.40})")
        rows.append(row)
    return rows


def check_agrees(rows: list[dict], path: Path, update: int, global_step: int) -> None:
    """One-line :class:`ProgressError` unless the row of ``update`` has ``global_step``.

    The trainer appends a row before it saves the checkpoint of that update,
    so a run's ``progress.jsonl`` always holds the checkpoint's row; a row
    that is missing or counts other steps means the two files come from
    different runs (resuming would cut one with the other's counter).
    """
    if update == 0:
        return
    steps = [row["global_step"] for row in rows if row["update"] == update]
    if not steps:
        raise ProgressError(
            f"{path} has no row for update {update}, the checkpoint's; the two files do not "
            "belong to one run"
        )
    if steps[-1] != global_step:
        raise ProgressError(
            f"{path} has update {update} at step {steps[-1]}, the checkpoint at step "
            f"{global_step}; the two files do not belong to one run"
        )


def keep_until(path: Path, rows: list[dict], update: int) -> None:
    """Rewrite ``path`` (atomically) with the rows up to ``update``: drops those of lost updates."""
    atomic_write(path, "".join(json.dumps(row) + "\n" for row in rows if row["update"] <= update))


def explained_variance(pred: np.ndarray, target: np.ndarray) -> float:
    var = np.var(target)
    return float("nan") if var == 0 else float(1 - np.var(target - pred) / var)


@dataclass
class UpdateStats:
    """What one finished update logs (:func:`progress_record`)."""

    update: int  # 1-based
    global_step: int  # environment steps after the update
    lr: float
    losses: dict[str, float]  # ppo_update's means
    roll: Rollout
    returns: np.ndarray  # (S, E)
    rollout: RolloutStats


#: Fields of a ``progress.jsonl`` record that measure time: they differ between two
#: runs of the same seed, so identity checks (resume, Ray vs local) leave them out.
TIMING_KEYS = frozenset(
    {"env_steps_per_s", "updates_per_s", "learner_s", "learner_cpu_s", "rollout_cpu_s"}
)


def progress_record(stats: UpdateStats, update_s: float) -> dict:
    """One ``progress.jsonl`` row: losses, rewards, PSAR rates and episode means.

    ``team_reward`` is R, what PPO maximises (paper eq. reward_all), per step
    and environment; ``global_reward`` is its part r_g; ``reward/*`` are the
    other parts (``ego_softmin``, ``individual``, ``completion``, ``warning``:
    the mean warning term of the CAVs on the road, ``delay``: the delay term
    before its weight, ``tau``; ``ego_softmin`` and ``tau`` come from the
    team reward the envs emit (:mod:`diacc.envs.reward`), the others from its terms);
    ``individual`` is the mean ego reward r_e over the CAVs on the road, what
    the training curves' individual-reward panel plots (``ego_softmin``, its
    softmin-weighted sum, falls as tau anneals whatever the policy does);
    ``psar/*`` the share of CAV decisions on which each rule took effect;
    ``episode/*`` means over the episodes that ended in the rollout
    (``episode/return``: the sum of an episode's team rewards R).
    """
    roll, rollout = stats.roll, stats.rollout
    record = {
        **stats.losses,
        "update": stats.update,
        "global_step": stats.global_step,
        "tau": rollout.tau,
        "lr": stats.lr,
        "explained_variance": explained_variance(roll.values.ravel(), stats.returns.ravel()),
        "env_steps_per_s": roll.rewards.size / rollout.seconds,
        "updates_per_s": 1.0 / update_s,
        "worker_restarts": rollout.restarts,
        "team_reward": float(roll.rewards.mean()),
    }
    terms = {key: float(np.mean(values)) for key, values in rollout.reward_terms.items()}
    record["global_reward"] = terms.pop("global")
    record.update({f"reward/{key}": value for key, value in terms.items()})
    record["greedy_top_share"] = top_action_share(rollout.greedy)[1]  # 1: collapsed
    for name, count in zip(RULE_NAMES[1:], rollout.psar_counts, strict=True):
        record[f"psar/{name}"] = float(count / max(rollout.decisions, 1))
    if rollout.episodes:
        for key, value in rollout.episodes[0].items():
            if isinstance(value, (int, float)):
                finite = [ep[key] for ep in rollout.episodes if np.isfinite(ep[key])]
                record[f"episode/{key}"] = float(np.mean(finite)) if finite else float("nan")
    return record


def write_record(record: dict, writer: SummaryWriter, progress_path: Path) -> None:
    """Append a record to ``progress.jsonl`` and to TensorBoard (``train/`` unless grouped)."""
    for key, value in record.items():
        if key not in ("update", "global_step"):
            writer.add_scalar(key if "/" in key else f"train/{key}", value, record["global_step"])
    with open_append(progress_path) as fh:
        fh.write(json.dumps(record) + "\n")

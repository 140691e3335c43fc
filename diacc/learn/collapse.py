"""A learned policy that picks one action whatever it sees, and the warning that names it.

A few seeds of a training run end *greedy-collapsed*: the actor's argmax is the
same action on (almost) every decision: 4 of the 18 runs of the paper's w_e
study (docs/results/paper-convergence.md), three on *right* (the CAVs queue for
the lane to their right and the delay doubles), one on *accelerate*. Such a seed's
rows in ``episodes.csv`` look like any other policy's, and a table that pools
seeds mixes it in silently; so an evaluation of a checkpoint counts the actions
its policy picks (:attr:`diacc.envs.episode.EpisodeDriver.picked`, before
PSAR refines them) and logs one warning when one action holds
:data:`COLLAPSE_SHARE` of them. Training runs the same check on every update:
the rollout counts the actor's argmax on every decision of a living CAV
(:attr:`diacc.learn.ppo.RolloutStats.greedy`, what a greedy evaluation of the
networks would pick), ``progress.jsonl`` records the top action's share
(``greedy_top_share``), and the run log warns at each checkpoint of a collapsed
policy (or says the check passed).

The counts are not stored in ``episodes.csv``: a resumed evaluation pools only
the episodes it plays, and one that skips every cell says nothing.

Scripted policies are left out: ``accelerate`` is one action by design, and
the policies that send no commands answer ``remain`` for every CAV.
"""

from __future__ import annotations

import numpy as np

from diacc.envs.actions import ACTION_NAMES

#: Share of the decisions one action must hold for a policy to count as collapsed. A
#: policy that drives well changes lane on 12-24 % of its decisions on the training
#: cell (docs/results/paper-convergence.md); the collapsed seeds there reach 100 %.
COLLAPSE_SHARE = 0.99
#: Fewest decisions the share is read from: a few steps say nothing about a policy.
MIN_DECISIONS = 200


def top_action_share(picked: np.ndarray) -> tuple[int, float]:
    """The action picked most often in counts ``picked`` (A,) and its share (nan: none)."""
    picked = np.asarray(picked, np.int64)
    total = int(picked.sum())
    top = int(picked.argmax())
    return top, (picked[top] / total if total else float("nan"))


def collapse_warning(
    label: str, picked: np.ndarray, where: str = "in this evaluation"
) -> str | None:
    """The one-line warning for action counts ``picked`` (A,) that are one action's, else None."""
    picked = np.asarray(picked, np.int64)  # (A,)
    total = int(picked.sum())
    if total < MIN_DECISIONS:
        return None
    top = int(picked.argmax())
    share = picked[top] / total
    if share < COLLAPSE_SHARE:
        return None
    return (
        f"{label} picked {ACTION_NAMES[top]!r} on {share:.1%} of its {total:,} decisions "
        f"{where}: a collapsed policy (one action whatever it sees); its rows "
        "are that one action's, not a driving skill's; check its other seeds "
        "(docs/guide/reproducing.md#collapsed-policies)"
    )

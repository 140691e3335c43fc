"""PSAR-aware action masks: the actions PSAR would execute unchanged (``psar_actions="masked"``).

With the paper's literal reading the actor samples any of the 5 actions and
PSAR overrides the unsafe ones, so the policy gradient is taken on actions
that never happened (how often PSAR rewrote the shipped agents' decisions:
docs/concepts/learning-options.md). Masking them out of the distribution before sampling makes the
sampled action the executed one and lets greedy evaluation pick the best
*allowed* action instead of repeating a suppressed one (the deadlock at lane
ends). The mask runs PSAR (:func:`diacc.envs.psar.psar`, unchanged) once on all
5 candidates for all CAVs of all envs (the state tiled five times), on the
state the decision is taken in:

* a candidate is allowed when PSAR returns it as the action (Decel-LC and a
  stronger Force-Brake keep the action and are allowed: they only add
  braking);
* CAV-to-CAV lane-change coordination is off while masking: it depends on the
  *other* CAVs' proposals, which are not known before sampling (every CAV
  proposing the same candidate would cancel lane changes that are fine). The
  executed step still coordinates, so a sampled lane change can be cancelled;
* the mask is never all False: if no candidate survives, the action PSAR
  makes of ``remain`` is allowed; CAVs off the road allow everything.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diacc.config import EnvConfig
from diacc.envs.actions import ACTION_NAMES, REMAIN
from diacc.envs.lateral_frame import MIRRORED_ACTION, is_mirrored
from diacc.envs.observation import ActorObs
from diacc.envs.psar import psar
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, take


def psar_action_mask(
    state: TrafficState, cav_index: np.ndarray, config: EnvConfig, road: Map
) -> np.ndarray:
    """(E, C, 5) bool: candidate actions PSAR would execute unchanged (module docstring).

    ``state`` is a batch of E envs (:mod:`diacc.sim.state`), ``cav_index`` its
    (E, C) agent slots.
    """
    cfg = dataclasses.replace(config.psar, coordinate_lane_changes=False)
    cav_index = np.asarray(cav_index)
    n_actions = len(ACTION_NAMES)
    # One PSAR call for every candidate: the batch tiled candidate-major to (5 E, V).
    tiled = TrafficState.concat([state] * n_actions)  # (5 E, V): env e of copy j is j E + e
    slots = np.tile(cav_index, (n_actions, 1))  # (5 E, C)
    candidate = np.repeat(np.arange(n_actions), state.n_envs)[:, None]  # (5 E, 1)
    proposed = np.broadcast_to(candidate, slots.shape)  # (5 E, C)
    refined = psar(tiled, slots, proposed, cfg, road, config.sim).action  # (5 E, C)
    refined = np.moveaxis(refined.reshape(n_actions, *cav_index.shape), 0, -1)  # (E, C, 5)
    allowed = refined == np.arange(n_actions)  # (E, C, 5)
    none_left = ~allowed.any(axis=-1)  # (E, C)
    fallback = np.eye(n_actions, dtype=bool)[refined[..., REMAIN]]  # (E, C, 5)
    allowed |= none_left[..., None] & fallback
    alive = take(state.active, cav_index)  # (E, C)
    return allowed | ~alive[..., None]


def with_action_mask(
    actor: ActorObs, state: TrafficState, cav_index: np.ndarray, config: EnvConfig, road: Map
) -> ActorObs:
    """``actor`` with its ``action_mask`` set as ``config.psar_actions`` asks (in place).

    ``state`` and ``road`` are the world's; the mask is in the agents' lateral
    frame, like the actions it masks (:mod:`diacc.envs.lateral_frame`).
    """
    if config.psar_actions == "masked":
        mask = psar_action_mask(state, cav_index, config, road)  # (..., C, 5) world frame
        if is_mirrored(road, config.obs.lateral_frame):
            mask = mask[..., MIRRORED_ACTION]
        actor.action_mask = mask
    return actor


def masked_logits(logits, action_mask):
    """Logits (..., 5) with the disallowed actions at the dtype's lowest value.

    Not ``-inf``: a finite floor keeps the entropy and the log-probs of the
    PPO replay finite (a masked action then has probability exp(-3e38) = 0).
    """
    import torch

    return logits.masked_fill(~action_mask, torch.finfo(logits.dtype).min)

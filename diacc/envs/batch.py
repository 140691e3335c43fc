"""The step of E environments, written once: decide -> simulate -> observe -> reward -> end.

:class:`EnvBatch` holds E episodes of one map and configuration as one typed
state with a leading env axis (:class:`EpisodeState`) and advances them all
in one :meth:`EnvBatch.step`:

1. :func:`decide`: PSAR refines the actions the actors proposed (or, without
   PSAR, the road's lane-change rule filters them) and makes backend commands;
2. the simulations advance one decision step (:class:`Simulators`);
3. agent slots are freed and refilled (CAVs that enter in a ``demand``
   scenario; :mod:`diacc.envs.env`, "Agent slots");
4. observations (:class:`~diacc.envs.observation.ObservationBuilder` over the
   batch), the reward terms that need no temperature
   (:func:`~diacc.envs.reward.reward_terms`), the safety events the metrics
   count, and each episode's end: a collision (unless ``SimConfig.on_collision``
   removes the vehicles that collided and goes on) or every vehicle gone
   (terminated), or ``episode_steps`` (truncated).

Everything that plays diacc is a thin adapter over it: the PettingZoo
:class:`~diacc.envs.env.BottleneckEnv` is a batch of one, every vector env
(:mod:`diacc.envs.vector`) a batch per map plus automatic resets, seeds and
episode metrics. Results are those of E environments stepped alone: every
computation is per env along the leading axis (``tests/test_vector.py``
compares them field by field).

The simulations are either one batched backend holding all E envs
(``highway``: one array program) or E backends stepped one after another
(``sumo``: each libsumo in its own process); both hand on one (E, V)
:class:`~diacc.sim.state.TrafficState`. A backend that fails
(:class:`~diacc.sim.backends.base.BackendError`) does not stop the others: its
env is reported ``crashed`` and its row keeps the state before the step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from diacc.config import EnvConfig
from diacc.envs.action_mask import with_action_mask
from diacc.envs.actions import (
    ACTION_LANE_OFFSET,
    REMAIN,
    action_speed_change_mps,
    lane_change_allowed,
)
from diacc.envs.lateral_frame import is_mirrored, mirror_actions
from diacc.envs.observation import ActorObs, CriticState, ObservationBuilder
from diacc.envs.psar import PSARResult, psar
from diacc.envs.reward import reward_terms
from diacc.envs.safety import safety_critical_events
from diacc.envs.step import Transition
from diacc.records import Batched, per_env, per_env_record
from diacc.sim.backends.base import Backend, BackendError, CavCommands
from diacc.sim.maps import Map
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState, stack_last, take, take_last


# ----------------------------------------------------------------------------- 1. decide
@dataclass
class Decision:
    """What :func:`decide` made of the proposed actions, (E, C) (C = agent slots)."""

    proposed: np.ndarray  # (E, C) int64 actor's actions
    refined: np.ndarray  # (E, C) int64 actions to execute
    rule: np.ndarray  # (E, C) int8 last PSAR rule that took effect (0 none)
    rule_mask: np.ndarray  # (E, C) int8 bitmask of the rules that took effect
    psar: PSARResult | None  # full PSAR result, (E, C) fields (None when PSAR is off)
    commands: CavCommands  # what the backends are asked to do, (E, V) arrays


def decide(
    state: TrafficState,
    cav_index: np.ndarray,
    actions: np.ndarray,
    config: EnvConfig,
    road: Map,
) -> Decision:
    """PSAR's refinement of the proposed actions and the backend commands they make.

    For a batch of states with (E, C) ``cav_index`` and ``actions``
    (:mod:`diacc.sim.state`); the decision has the same shapes.
    A lane change the road does not allow is not made, with or without PSAR.
    """
    proposed = np.asarray(actions, dtype=np.int64).reshape(cav_index.shape)
    # The agents act in their lateral frame (diacc.envs.lateral_frame), PSAR and the backend
    # in the world's: ``world`` is what the agents asked for, in the world's frame.
    mirrored = is_mirrored(road, config.obs.lateral_frame)
    world = mirror_actions(proposed) if mirrored else proposed
    alive = take(state.active, cav_index)  # (..., C)
    no_rule = np.zeros(cav_index.shape, np.int8)
    sim = config.sim
    if config.psar_enabled:
        result = psar(state, cav_index, world, config.psar, road, sim)
        executed = np.where(alive, result.action, REMAIN)
        rule = np.where(alive, result.rule, 0).astype(np.int8)
        rule_mask = np.where(alive, result.rule_mask, 0).astype(np.int8)
        speed_change_mps = np.where(alive, result.speed_change_mps, 0.0)
    else:
        # Without PSAR a lane change the road does not allow is still not made
        # (the same rule as PSAR and the backends), so the executed action is honest.
        allowed = lane_change_allowed(state, cav_index, world, road, sim)
        is_lc = ACTION_LANE_OFFSET[world] != 0
        result, executed = None, np.where(alive & (allowed | ~is_lc), world, REMAIN)
        rule, rule_mask = no_rule, no_rule
        speed_change_mps = action_speed_change_mps(executed, sim)
    lane_change = np.zeros(state.x_m.shape, np.int8)  # (..., V)
    speed_change = np.zeros(state.x_m.shape, np.float64)
    # Added, not put: empty slots may share a vehicle (not on the road) and add 0 there.
    where = (*np.indices(cav_index.shape)[:-1], cav_index)
    np.add.at(lane_change, where, ACTION_LANE_OFFSET[executed].astype(np.int8))
    np.add.at(speed_change, where, speed_change_mps)
    # CAVs on the road without a slot (demand: more than cav_slots at once) drive
    # themselves: NaN is "no command" (diacc.sim.backends.base).
    driven = np.zeros(state.x_m.shape, bool)  # (..., V)
    np.logical_or.at(driven, where, alive)
    speed_change[state.is_cav & state.active & ~driven] = np.nan
    commands = CavCommands(lane_change, speed_change)
    refined = mirror_actions(executed) if mirrored else executed  # back in the agents' frame
    return Decision(proposed, refined, rule, rule_mask, result, commands)


# ----------------------------------------------------------------------------- 2. simulate
class Simulators:
    """E simulations of one map, stepped as one: (E, V) commands in, one (E, V) state out.

    Either one backend whose ``vector_mode`` is ``"batched"`` and that holds
    every env (the ``highway`` backend), or one backend per env, stepped one
    after another; every backend speaks batches (:mod:`diacc.sim.backends.base`).
    """

    def __init__(self, backends: Sequence[Backend]) -> None:
        first = backends[0]
        self.batched = len(backends) == 1 and first.vector_mode == "batched"
        self.backends = list(backends)
        self.road: Map = first.road
        self.n_envs = first.n_envs if self.batched else len(backends)
        self._latest: list[TrafficState | None] = [None] * self.n_envs  # one after another
        #: The failure of each env whose simulator crashed in the last step.
        self.errors: dict[int, BackendError] = {}

    def reset(self, e: int, scenario: Scenario, seed: int) -> TrafficState:
        """Start env ``e``'s simulation anew; its first state (a batch of one)."""
        if self.batched:
            return self.backends[0].reset(scenario, seed, env=e)
        self._latest[e] = self.backends[e].reset(scenario, seed)
        return self._latest[e]

    def step(self, commands: CavCommands) -> tuple[TrafficState, np.ndarray]:
        """The (E, V) state after one step and the (E,) envs whose simulator crashed
        (their rows hold the state before the step; :attr:`errors` says why)."""
        crashed = np.zeros(self.n_envs, bool)
        self.errors = {}
        if self.batched:
            return self.backends[0].step(commands), crashed
        for e, backend in enumerate(self.backends):
            try:
                self._latest[e] = backend.step(commands.env(e))
            except BackendError as err:
                crashed[e], self.errors[e] = True, err
        return TrafficState.concat(self._latest), crashed

    def close(self) -> None:
        for backend in self.backends:
            backend.close()


# ----------------------------------------------------------------------------- the state
@dataclass
class EpisodeState(Batched):
    """diacc's state of E episodes besides the observation history, one row per env (a
    :class:`~diacc.records.Batched` record: new episodes' rows are set as declared).

    The history of the last T states that the observations read is the
    batch's :class:`~diacc.envs.observation.ObservationBuilder`'s.
    """

    traffic: TrafficState = per_env_record()  # (E, V) the simulators' latest, world's frame
    steps: np.ndarray = per_env("E")  # int64 decision steps of the episode so far
    cav_ordinal: np.ndarray = per_env("E, V")  # int64 k of the k-th CAV (PettingZoo cav_k)
    slot_vehicle: np.ndarray = per_env("E, C")  # int64 each slot's occupant, -1 none
    last_vehicle: np.ndarray = per_env("E, C")  # int64 each slot's latest occupant, -1 never
    cav_index: np.ndarray = per_env("E, C")  # int64 vehicle each slot points at (empty: off road)
    slot_start: np.ndarray = per_env("E, C")  # bool a new CAV took the slot at the last step
    unserved_cavs: np.ndarray = per_env("E")  # int64 CAVs on the road without a slot
    action_memory: np.ndarray = per_env("E, C, 2")  # int64 proposed, refined action last step
    last_refined: np.ndarray = per_env("E, V")  # int64 refined action each vehicle executed last
    wrecked: np.ndarray = per_env("E, V")  # bool collided this episode (on_collision "remove")

    @classmethod
    def start(cls, traffic: TrafficState, n_slots: int) -> EpisodeState:
        """Every env at the first state of an episode, no slot taken yet."""
        n_envs, n_vehicles = traffic.x_m.shape
        return cls(
            traffic=traffic,
            steps=np.zeros(n_envs, np.int64),
            cav_ordinal=np.cumsum(traffic.is_cav, axis=-1) - 1,
            slot_vehicle=np.full((n_envs, n_slots), -1, np.int64),
            last_vehicle=np.full((n_envs, n_slots), -1, np.int64),
            cav_index=np.zeros((n_envs, n_slots), np.int64),
            slot_start=np.zeros((n_envs, n_slots), bool),
            unserved_cavs=np.zeros(n_envs, np.int64),
            action_memory=np.zeros((n_envs, n_slots, 2), np.int64),
            last_refined=np.zeros((n_envs, n_vehicles), np.int64),
            wrecked=np.zeros((n_envs, n_vehicles), bool),
        )


# ----------------------------------------------------------------------------- the batch
class EnvBatch:
    """E episodes of one map and configuration, advanced by one step function."""

    def __init__(self, config: EnvConfig, sims: Simulators) -> None:
        self.config, self.sims, self.road = config, sims, sims.road
        self.n_envs, self.n_cavs = sims.n_envs, config.scenario.n_slots
        self.builder = ObservationBuilder(
            self.road,
            config.obs,
            config.sim.episode_steps,
            compact_critic=config.scenario.kind == "demand",
        )
        self.state: EpisodeState | None = None

    def reset(self, rows: Sequence[int], seeds: Sequence[int]) -> None:
        """Start new episodes in envs ``rows`` with ``seeds``; the other envs go on.

        The first reset starts every env; later ones need the vehicle count the
        batch holds (the scenario's).
        """
        rows = np.asarray(rows, np.int64)
        firsts = [
            self.sims.reset(int(e), self.config.scenario, int(s))
            for e, s in zip(rows, seeds, strict=True)
        ]
        if self.state is None or len(rows) == self.n_envs:
            if not np.array_equal(rows, np.arange(self.n_envs)):
                raise ValueError(f"the first reset starts every env in order, got rows {rows}")
            self.state = EpisodeState.start(TrafficState.concat(firsts), self.n_cavs)
            self.builder.reset(self.state.traffic)
        else:
            st = self.state
            for e, first in zip(rows, firsts, strict=True):
                if first.n_vehicles != st.traffic.n_vehicles:
                    raise ValueError(
                        f"env {e}'s new episode has {first.n_vehicles} vehicles, the batch "
                        f"holds {st.traffic.n_vehicles}"
                    )
            st.set_rows(rows, EpisodeState.start(TrafficState.concat(firsts), self.n_cavs))
            self.builder.reset_rows(rows, st.traffic)
        self._fill_slots(rows)

    def step(self, actions: np.ndarray) -> Transition:
        """Advance every env one decision step with the (E, C) proposed actions (the
        step's :class:`~diacc.envs.step.Transition`, with its state, PSAR result and events)."""
        st, cfg = self.state, self.config
        assert st is not None, "reset() before step()"
        decision = decide(st.traffic, st.cav_index, actions, cfg, self.road)  # 1.
        traffic, crashed = self.sims.step(decision.commands)  # 2.
        st.steps += 1
        st.traffic = traffic
        self.builder.push(traffic)
        st.action_memory = stack_last([decision.proposed, decision.refined])
        st.last_refined[np.arange(self.n_envs)[:, None], st.cav_index] = decision.refined
        self._fill_slots(np.arange(self.n_envs))  # 3.
        actor, critic = self.observe()  # 4.
        terms = reward_terms(traffic, st.cav_index, self.road, cfg.reward)
        collided = np.zeros(self.n_envs, bool)
        collided[traffic.collisions[:, 0]] = True
        if traffic.collisions.shape[0]:
            st.wrecked |= traffic.collided
        if cfg.sim.on_collision == "remove":  # the wrecks leave the road; the others go on
            collided[:] = False
        terminated = collided | (traffic.arrived | st.wrecked).all(axis=-1)
        return Transition(
            actor_obs=actor,
            critic_state=critic,
            terms=terms,
            refined_action=decision.refined,
            psar_rule=decision.rule,
            psar_rule_mask=decision.rule_mask,
            slot_start=st.slot_start.copy(),
            terminated=terminated,
            truncated=~terminated & (st.steps >= cfg.sim.episode_steps),
            crashed=crashed,
            team=None,  # the vector envs and the PettingZoo env score it (diacc.envs.step)
            state=traffic,
            psar=decision.psar,
            critical=safety_critical_events(traffic, cfg.events).any,
        )

    def observe(self, rows: np.ndarray | None = None) -> tuple[ActorObs, CriticState]:
        """Observations of the current states: every env's, or those of envs ``rows``."""
        st = self.state if rows is None else self.state.rows(rows)
        if rows is None:
            actor = self.builder.actor(st.cav_index, st.action_memory, st.last_refined)
            critic = self.builder.critic()
        else:
            actor, critic = self.builder.observe_rows(
                rows, st.cav_index, st.action_memory, st.last_refined
            )
        return with_action_mask(actor, st.traffic, st.cav_index, self.config, self.road), critic

    def _fill_slots(self, rows: np.ndarray) -> None:
        """In envs ``rows``: free the slots of CAVs gone before this step, give CAVs on the
        road without a slot the free ones, in order of entry (:mod:`diacc.envs.env`)."""
        st, traffic = self.state, self.state.traffic
        occupant = st.slot_vehicle[rows]  # (R, C)
        active = traffic.active[rows]  # (R, V)
        # An arriving CAV keeps its slot this step, and so does a wreck taken off the road
        # (on_collision = "remove"): the reward scores the slot's trip end.
        present = active | traffic.arrived_now[rows] | traffic.collided[rows]
        stays = (occupant >= 0) & take_last(present, np.maximum(occupant, 0))
        occupant = np.where(stays, occupant, -1)
        held = np.zeros(active.shape, bool)  # (R, V) CAVs that keep a slot
        r_stay, c_stay = np.nonzero(stays)
        held[r_stay, occupant[r_stay, c_stay]] = True
        waiting = active & traffic.is_cav[rows] & ~held  # (R, V)
        unserved = waiting.sum(axis=-1)
        refilled = np.zeros(occupant.shape, bool)
        # Only where a CAV waits and a slot is free: at resets and as CAVs enter (demand).
        for r in np.flatnonzero(waiting.any(axis=-1) & (~stays).any(axis=-1)):
            cavs, free = np.flatnonzero(waiting[r]), np.flatnonzero(~stays[r])
            n_new = min(len(free), len(cavs))
            occupant[r, free[:n_new]] = cavs[:n_new]
            refilled[r, free[:n_new]] = True
            unserved[r] = len(cavs) - n_new
        last = np.where(occupant >= 0, occupant, st.last_vehicle[rows])
        # An empty slot points at its last occupant (gone for good) or, never used, at a
        # vehicle off the road: one exists, since then some CAV is not on the road.
        off_road = np.argmax(~active, axis=-1)  # (R,)
        st.cav_index[rows] = np.where(last < 0, off_road[:, None], last)
        st.slot_vehicle[rows], st.last_vehicle[rows] = occupant, last
        st.action_memory[rows] = np.where(refilled[..., None], 0, st.action_memory[rows])
        st.slot_start[rows], st.unserved_cavs[rows] = refilled, unserved

    def close(self) -> None:
        self.sims.close()

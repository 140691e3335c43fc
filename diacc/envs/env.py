"""The multi-agent bottleneck environment (PettingZoo ``ParallelEnv``) over any backend.

One environment = one backend simulation + the shared observation builder +
PSAR + the reward. Agents are the scenario's CAVs (``"cav_0"`` ...), in the
order of their vehicle indices. Each step:

1. the actor proposes a discrete action per CAV
   {0 remain, 1 left, 2 right, 3 accelerate, 4 decelerate};
2. PSAR (paper Algorithm 1) refines it, unless ``use_psar`` is off (the
   ``diacc-nopsar`` ablation);
3. the refined action becomes a backend command (lane change +-1, speed change
   +-``speed_change_mps``; Decel-LC brakes by ``b_lc`` during its lane change,
   Force-Brake by what PSAR asks, see :func:`diacc.envs.psar.psar`). A lane
   change the road does not allow here is not made, with or without PSAR;
4. the backend advances one decision step and returns a TrafficState, from
   which the observations, the reward and the events are built.

**Reward and temperature.** The step's reward terms
(:func:`~diacc.envs.reward.reward_terms`: each CAV's ego reward, the global,
completion and delay terms) need no temperature and are what
:class:`StepResult` carries for a trainer. The team reward
:meth:`BottleneckEnv.reward_of` (the PettingZoo ``rewards``) aggregates them with
:func:`~diacc.envs.reward.team_reward` at the env's own softmin temperature
:attr:`BottleneckEnv.temperature`, ``tau_init`` unless set; the env never
anneals it. A trainer that anneals tau (:mod:`diacc.learn.mappo`) makes the
team reward from the terms at its own temperature, so a training step never
computes the env's.

The episode terminates on a collision or when every vehicle has left, and is
truncated at ``episode_steps``. A CAV that has left the route is done and is
never revived.

**Agent slots.** The arrays have C = ``Scenario.n_slots`` agent slots. In a
release every CAV has its own slot for the whole episode (slot k = the k-th
CAV). In a ``demand`` scenario CAVs enter and leave: a CAV that enters takes
the first free slot (CAVs in order of entry), keeps it until it leaves, and
its slot stays pointed at it for the step it arrives (so the reward sees the
arrival) and is free from the next step on. A refilled slot is flagged in
``StepResult.slot_start``: the policy starts that slot's recurrent state
afresh. An empty slot points at a vehicle that is not on the road, so every
consumer of ``cav_index`` sees it dead (``alive`` False) without knowing
about slots. CAVs that find no free slot (more than ``cav_slots`` at once)
drive themselves meanwhile (no command, :mod:`diacc.sim.backends.base`) and are
counted in :attr:`BottleneckEnv.unserved_cavs`.
PettingZoo names agents by CAV, not slot: ``possible_agents`` are
``cav_0 .. cav_{K-1}`` for the K CAVs of the episode in order of entry, and
``agents`` are those on the road and in a slot now.

Two APIs share the same code path: the PettingZoo dict API (``reset`` /
``step``) for users and API tests, and the batched API (:meth:`reset_arrays` /
:meth:`step_arrays`) that the trainer uses to avoid per-agent dicts. A step is
:meth:`decide` (steps 1-3), the backend's step, then :meth:`advance` (step 4):
a vector of envs over one batched backend (:mod:`diacc.envs.vector`) calls the two
halves around a single batched backend step.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from diacc.config import EnvConfig, preset_road
from diacc.envs.action_mask import with_action_mask
from diacc.envs.actions import (
    ACTION_LANE_OFFSET,
    ACTION_NAMES,
    REMAIN,
    action_speed_change_mps,
    lane_change_allowed,
)
from diacc.envs.lateral_frame import is_mirrored, mirror_actions
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.observation import ActorObs, CriticState, ObservationBuilder
from diacc.envs.psar import PSARResult, psar
from diacc.envs.reward import RewardTerms, reward_terms, team_reward
from diacc.envs.spaces import agent_observation, check_format, observation_space, state_space
from diacc.errors import DiaccError
from diacc.sim.backends.base import Backend, CavCommands, make_backend
from diacc.sim.maps import Map, load_map
from diacc.sim.state import TrafficState, take

__all__ = ["ACTION_NAMES", "BottleneckEnv", "EnvConfig", "RenderModeError", "StepResult"]

#: The episode-end metrics every agent's ``infos`` carries on the last step (see
#: :meth:`BottleneckEnv.step`), a subset of :class:`diacc.envs.metrics.EpisodeMetrics`.
INFO_METRICS = (
    "mean_speed_mps",
    "mean_cav_speed_mps",
    "mean_hdv_speed_mps",
    "p_we",
    "p_sce",
    "n_collisions",
    "arrived_fraction",
    "mean_travel_time_s",
    "episode_steps",
    "n_vehicles",
)


class RenderModeError(DiaccError, ValueError):
    """A render mode this environment cannot honour here; one line."""


@dataclass
class Decision:
    """What :func:`decide` made of the proposed actions (C = CAV slots; (E, ...) in a batch)."""

    proposed: np.ndarray  # (C,) int64 actor's actions
    refined: np.ndarray  # (C,) int64 actions to execute
    rule: np.ndarray  # (C,) int8 last PSAR rule that took effect (0 none)
    rule_mask: np.ndarray  # (C,) int8 bitmask of the rules that took effect
    psar: PSARResult | None  # full PSAR result (None when PSAR is off)
    commands: CavCommands  # what the backend is asked to do, (V,) arrays

    def env(self, e: int) -> Decision:
        """Env ``e``'s decision out of a batch's."""
        psar = None
        if self.psar is not None:
            psar = PSARResult(*(getattr(self.psar, f.name)[e] for f in fields(PSARResult)))
        commands = CavCommands(self.commands.lane_change[e], self.commands.speed_change_mps[e])
        return Decision(
            self.proposed[e], self.refined[e], self.rule[e], self.rule_mask[e], psar, commands
        )


def decide(
    state: TrafficState,
    cav_index: np.ndarray,
    actions: np.ndarray,
    config: EnvConfig,
    road: Map,
) -> Decision:
    """PSAR's refinement of the proposed actions and the backend commands they make.

    Steps 1-3 of the module docstring, for one state with (C,) ``cav_index`` and
    ``actions``, or for a batch of states with (E, C) ones (:mod:`diacc.sim.state`).
    """
    proposed = np.asarray(actions, dtype=np.int64).reshape(cav_index.shape)
    # The agents act in their lateral frame (diacc.envs.lateral_frame), PSAR and the backend
    # in the world's: ``world`` is what the agents asked for, in the world's frame.
    mirrored = is_mirrored(road, config.obs.lateral_frame)
    world = mirror_actions(proposed) if mirrored else proposed
    alive = take(state.active, cav_index)  # (..., C)
    no_rule = np.zeros(cav_index.shape, np.int8)
    sim = config.sim
    if config.use_psar:
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
        speed_change_mps = action_speed_change_mps(executed, sim.speed_change_mps)
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


@dataclass
class StepResult:
    """What :meth:`BottleneckEnv.step_arrays` returns (C = CAV slots)."""

    actor_obs: ActorObs
    critic_state: CriticState
    terminated: bool
    truncated: bool
    alive: np.ndarray  # (C,) bool: CAV on the road after the step (the reward's mask)
    refined_action: np.ndarray  # (C,) int64 action executed
    psar_rule: np.ndarray  # (C,) int8 last PSAR rule that took effect (0 none)
    psar_rule_mask: np.ndarray  # (C,) int8 bitmask of the rules that took effect
    psar: PSARResult | None  # full PSAR result (None when PSAR is off)
    state: TrafficState
    reward_terms: dict[str, float]  # logged parts of the reward that need no temperature
    slot_start: np.ndarray  # (C,) bool: a new CAV took the slot; its next action starts afresh
    # What team_reward aggregates (with ``alive``), at any temperature:
    ego: np.ndarray  # (C,) ego reward r_e of each CAV slot (0 off the road)
    global_reward: float  # r_g
    completion: float  # r_done
    delay: float  # delay term before its weight


class BottleneckEnv(ParallelEnv):
    """CAVs crossing a highway bottleneck among HDVs (see module docstring).

    Every agent's reward is the team reward at the softmin temperature
    :attr:`temperature` (``tau_init`` unless set; never annealed here). A trainer
    that anneals tau makes the team reward from :class:`StepResult`'s terms with
    :func:`~diacc.envs.reward.team_reward` (as :mod:`diacc.learn.mappo` does).
    """

    metadata = {
        "name": "diacc_bottleneck_v0",
        "render_modes": ["human", "rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: EnvConfig | None = None,
        render_mode: str | None = None,
        backend: Backend | None = None,
        observation_format: str = "dict",
    ) -> None:
        """``backend``: the simulator to run on (e.g. one env of a batch), by default a new
        one of ``config.backend`` on ``config.map``. ``render_mode``: ``None``,
        ``"rgb_array"`` (:meth:`render` returns a frame) or ``"human"`` (a window,
        refreshed every step; refused without a display). ``observation_format``:
        ``"dict"`` or ``"flat"`` (:mod:`diacc.envs.spaces`)."""
        self.config = config or EnvConfig()
        self.render_mode = check_render_mode(render_mode)
        self.observation_format = check_format(observation_format)
        if backend is None:
            road = preset_road(load_map(self.config.map), self.config.sim.style_preset)
            backend = make_backend(self.config.backend, road, self.config.sim)
        self.backend: Backend = backend
        self.road: Map = backend.road
        self.builder = ObservationBuilder(
            self.road,
            self.config.obs,
            self.config.sim.episode_steps,
            compact_critic=self.config.scenario.kind == "demand",
        )
        self.n_cavs = self.config.scenario.n_slots  # C agent slots
        self.possible_agents = [f"cav_{k}" for k in range(self.config.scenario.n_cavs)]
        self.agents: list[str] = []
        #: Softmin temperature of :meth:`reward_of` (module docstring): fixed,
        #: ``tau_init`` unless set; a trainer that anneals tau makes its own team reward.
        self.temperature = self.config.reward.tau_init
        self.state_: TrafficState | None = None
        self._viewer = None  # diacc.sim.viewer.Viewer, made by the first render()
        self._window = None  # diacc.sim.viewer.Window of render_mode "human"
        self._recorder: EpisodeRecorder | None = None  # episode metrics of the dict API
        self._seed: int | None = None
        # Spaces are the same for every agent: built once, returned as the same object.
        spec = self.builder.spec()
        self._dict_space = observation_space(spec, "dict")
        self._observation_space = observation_space(spec, self.observation_format)
        self._action_space = gymnasium.spaces.Discrete(len(ACTION_NAMES))
        self.state_space = state_space(spec)

    # ------------------------------------------------------------------ batched API
    def reset_arrays(self, seed: int | None = None) -> tuple[ActorObs, CriticState]:
        """Start an episode; returns observations for all CAV slots and the critic state."""
        if seed is None:
            seed = 0 if self._seed is None else self._seed + 1
        self._seed = seed
        state = self.backend.reset(self.config.scenario, seed)
        self.cav_ordinal = np.cumsum(state.is_cav) - 1  # (V,) k of the k-th CAV (agent cav_k)
        self.slot_vehicle = np.full(self.n_cavs, -1, np.int64)  # (C,) occupant, -1 none
        self._last_vehicle = np.full(self.n_cavs, -1, np.int64)  # (C,) latest occupant
        self.action_memory = np.zeros((self.n_cavs, 2), np.int64)  # proposed, refined
        self.last_refined = np.zeros(state.n_vehicles, np.int64)
        self.steps = 0
        self.state_ = state
        self.builder.reset(state)
        self.slot_start = self._fill_slots(state)
        self.agents = self._live_agents(state)
        self._recorder = None  # the dict API's reset() starts one; the batched API needs none
        return self._observe()

    def _fill_slots(self, state: TrafficState) -> np.ndarray:
        """Free the slots of CAVs gone before this step, give CAVs on the road without
        a slot the free ones (module docstring); sets :attr:`cav_index`, returns the
        (C,) refilled slots."""
        occupant = self.slot_vehicle
        held = np.maximum(occupant, 0)
        stays = (occupant >= 0) & (state.active[held] | state.arrived_now[held])  # (C,)
        waiting = np.flatnonzero(state.active & state.is_cav)  # in order of entry
        waiting = waiting[~np.isin(waiting, occupant[stays])]
        free = np.flatnonzero(~stays)
        n_new = min(len(free), len(waiting))
        occupant = np.where(stays, occupant, -1)
        occupant[free[:n_new]] = waiting[:n_new]
        refilled = np.zeros(self.n_cavs, bool)
        refilled[free[:n_new]] = True
        self.unserved_cavs = len(waiting) - n_new  # CAVs on the road without a slot
        self.slot_vehicle = occupant
        self._last_vehicle = np.where(occupant >= 0, occupant, self._last_vehicle)
        # An empty slot points at its last occupant (gone for good) or, never used, at
        # any vehicle off the road: one exists, since then some CAV is not on the road.
        index = self._last_vehicle
        if (index < 0).any():
            index = np.where(index < 0, np.flatnonzero(~state.active)[0], index)
        self.cav_index = index.copy()  # (C,) vehicle index of each slot
        self.action_memory[refilled] = 0
        return refilled

    def _live_agents(self, state: TrafficState) -> list[str]:
        """PettingZoo names of the CAVs on the road that hold a slot."""
        live = self.slot_vehicle[self.slot_vehicle >= 0]
        live = np.sort(live[state.active[live]])
        return [f"cav_{k}" for k in self.cav_ordinal[live]]

    def step_arrays(self, actions: np.ndarray) -> StepResult:
        """Advance one decision step with proposed actions (C,) for every CAV slot."""
        decision = self.decide(actions)
        return self.advance(decision, self.backend.step(decision.commands))

    def decide(self, actions: np.ndarray) -> Decision:
        """:func:`decide` for this env's current state and proposed actions (C,)."""
        assert self.state_ is not None, "call reset before step"
        return decide(self.state_, self.cav_index, actions, self.config, self.road)

    def advance(self, decision: Decision, state: TrafficState) -> StepResult:
        """Observations, reward and episode end once the backend has executed ``decision``."""
        self.enter(decision, state)
        terms = reward_terms(state, self.cav_index, self.road, self.config.reward)
        return self.conclude(decision, state, *self._observe(), terms)

    def enter(self, decision: Decision, state: TrafficState) -> None:
        """Make ``state``, reached by executing ``decision``, the current one."""
        self.steps += 1
        self.state_ = state
        self.builder.push(state)
        self.action_memory = np.stack([decision.proposed, decision.refined], axis=1)
        self.last_refined[self.cav_index] = decision.refined
        self.slot_start = self._fill_slots(state)

    def conclude(
        self,
        decision: Decision,
        state: TrafficState,
        actor_obs: ActorObs,
        critic_state: CriticState,
        terms: RewardTerms,
    ) -> StepResult:
        """The step's result, given the observations and the reward terms of the state
        :meth:`enter` entered (which :meth:`ObservationBuilder.observe_batch` and
        :func:`~diacc.envs.reward.reward_terms` compute for many envs at once)."""
        # Every vehicle gone: none on the road and none still to enter (demand).
        terminated = bool(len(state.collisions) > 0 or state.arrived.all())
        truncated = bool(not terminated and self.steps >= self.config.sim.episode_steps)
        return StepResult(
            actor_obs=actor_obs,
            critic_state=critic_state,
            terminated=terminated,
            truncated=truncated,
            alive=state.active[self.cav_index].copy(),
            refined_action=decision.refined,
            psar_rule=decision.rule,
            psar_rule_mask=decision.rule_mask,
            psar=decision.psar,
            state=state,
            # The temperature's parts (ego_softmin, tau) are the trainer's to log.
            reward_terms={
                "individual": float(terms.ego[terms.alive].mean()) if terms.alive.any() else 0.0,
                "global": terms.global_reward,
                "completion": terms.completion,
                # Logged so that a learning curve shows whether closeness fires.
                "warning": float(terms.warning[terms.alive].mean()) if terms.alive.any() else 0.0,
                "delay": terms.delay,
            },
            slot_start=self.slot_start.copy(),
            ego=terms.ego,
            global_reward=terms.global_reward,
            completion=terms.completion,
            delay=terms.delay,
        )

    def reward_of(self, out: StepResult) -> float:
        """Team reward R_t (paper eq. reward_all) of a step at :attr:`temperature`."""
        parts = (out.ego, out.alive, out.global_reward, out.completion, out.delay)
        return float(team_reward(*parts, self.temperature, self.config.reward).total)

    def _observe(self) -> tuple[ActorObs, CriticState]:
        actor = self.builder.actor(self.cav_index, self.action_memory, self.last_refined)
        actor = with_action_mask(actor, self.state_, self.cav_index, self.config, self.road)
        return actor, self.builder.critic()

    # ------------------------------------------------------------------ PettingZoo API
    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        """One agent's observation space (:mod:`diacc.envs.spaces`; no reset needed)."""
        return self._observation_space
        spec = self.builder.spec()
        spaces = {}
        for name, (shape, dtype) in spec.actor_shapes(n_cavs=1).items():
            row = shape[1:]  # one agent's row
            if dtype == np.dtype(bool):
                spaces[name] = gymnasium.spaces.MultiBinary(row)
            elif dtype == np.int64:  # action codes
                spaces[name] = gymnasium.spaces.Box(0, spec.n_actions - 1, row, np.int64)
            else:
                spaces[name] = gymnasium.spaces.Box(-np.inf, np.inf, row, np.float32)
        self._observation_space = gymnasium.spaces.Dict(spaces)
        return self._observation_space

    def action_space(self, agent: str) -> gymnasium.spaces.Discrete:
        return self._action_space

    def _agent_slots(self) -> dict[str, int]:
        """Slot of each agent (CAV) that holds one now."""
        held = np.flatnonzero(self.slot_vehicle >= 0)
        return {f"cav_{self.cav_ordinal[self.slot_vehicle[i]]}": int(i) for i in held}

    def reset(self, seed: int | None = None, options: dict | None = None):
        actor_obs, _ = self.reset_arrays(seed)
        self._recorder = EpisodeRecorder(
            self.road, self.config.events, self.config.scenario.warmup_s
        )
        self._recorder.record(self.state_)
        slots = self._agent_slots()
        observations = {a: self._agent_obs(actor_obs, slots[a]) for a in self.agents}
        if self.render_mode == "human":
            self.render()
        return observations, {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        index = self._agent_slots()
        batch = np.zeros(self.n_cavs, np.int64)
        for agent, action in actions.items():
            if agent in index:
                batch[index[agent]] = action
        out = self.step_arrays(batch)
        if self._recorder is not None:
            self._recorder.record(out.state, psar=out.psar)
        acting = list(self.agents)
        ended = out.terminated or out.truncated
        # CAVs that took a slot in this step join (PettingZoo lets agents appear).
        index.update(self._agent_slots())
        joining = [] if ended else [a for a in self._live_agents(out.state) if a not in acting]
        observations, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        team = self.reward_of(out)
        for agent in acting + joining:
            i = index[agent]
            observations[agent] = self._agent_obs(out.actor_obs, i)
            rewards[agent] = team
            terms[agent] = out.terminated or not out.alive[i]
            truncs[agent] = out.truncated
            infos[agent] = {
                "refined_action": int(out.refined_action[i]),
                "psar_rule": int(out.psar_rule[i]),
                "collisions": out.state.collisions.copy(),
                "arrivals": out.state.arrivals.copy(),
            }
        self.agents = [] if ended else self._live_agents(out.state)
        if not self.agents and acting and self._recorder is not None:
            summary = self._recorder.summary()
            metrics = {key: getattr(summary, key) for key in INFO_METRICS}
            for agent in acting + joining:
                infos[agent]["episode_metrics"] = dict(metrics)
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terms, truncs, infos

    def state(self) -> np.ndarray:
        """Flattened critic state (PettingZoo convention for a centralised critic)."""
        critic = self.builder.critic()
        return np.concatenate(
            [np.asarray(getattr(critic, f.name), np.float32).ravel() for f in fields(critic)]
        )

    def render(self) -> np.ndarray | None:
        """What ``render_mode`` asks for: ``"rgb_array"`` returns an RGB frame (H, W, 3)
        uint8 of the current state (:class:`diacc.sim.viewer.Viewer`), ``"human"`` shows
        it in a window and returns ``None``. Without a render mode there is nothing
        to render: a one-line :class:`RenderModeError` (Gymnasium only warns, which
        hides the mistake)."""
        if self.render_mode is None:
            raise RenderModeError(
                "render() needs a render_mode; make the env with render_mode='rgb_array' "
                "(frames) or 'human' (a window)"
            )
        if self.state_ is None:
            return None
        if self._viewer is None:
            from diacc.sim.viewer import Viewer

            self._viewer = Viewer(self.road, self.config.sim)
        frame = self._viewer.draw(self.state_)
        if self.render_mode == "rgb_array":
            return frame
        if self._window is None:
            from diacc.sim.viewer import Window

            self._window = Window(f"diacc {self.config.map} ({self.config.backend})")
        self._window.show(frame)
        return None

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
        if self._window is not None:
            self._window.close()
            self._window = None
        self.backend.close()

    # ------------------------------------------------------------------ helpers
    def _agent_obs(self, actor_obs: ActorObs, i: int) -> dict[str, np.ndarray] | np.ndarray:
        return agent_observation(actor_obs, i, self._dict_space, self.observation_format)


def check_render_mode(render_mode: str | None) -> str | None:
    """``render_mode`` if this machine can honour it, else a one-line :class:`RenderModeError`.

    ``"human"`` needs a display (``DISPLAY`` or ``WAYLAND_DISPLAY`` on Linux);
    refusing it here beats a window that never appears.
    """
    modes = BottleneckEnv.metadata["render_modes"]
    if render_mode is not None and render_mode not in modes:
        raise RenderModeError(
            f"unknown render_mode {render_mode!r}; use one of: {', '.join(modes)} (or None)"
        )
    if render_mode == "human":
        from diacc.sim.viewer import display_available

        if not display_available():
            raise RenderModeError(
                "render_mode 'human' needs a display and none was found (DISPLAY is unset); "
                "use render_mode='rgb_array' and save the frames"
            )
    return render_mode

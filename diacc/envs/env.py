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

**Reward and temperature.** Each step emits the team reward R
(``Transition.reward``, every agent's PettingZoo reward) at the softmin
temperature the env is given, :attr:`BottleneckEnv.tau` (``tau_init`` until
set). The env counts no training progress: the schedule belongs to whoever
trains. :class:`AnnealTemperature` is the schedule for a trainer of another
library: it wraps the env and sets tau before each step from the env steps
taken through it, so that R is the one diacc's trainer trains on.
The step (:class:`~diacc.envs.step.Transition`, env 0's view of the batch's) also
carries the terms R is made of.

The episode terminates on a collision or when every vehicle has left, and is
truncated at ``episode_steps``. A CAV that has left the route is done and is
never revived.

**Agent slots.** The arrays have C = ``Scenario.n_slots`` agent slots. In a
release every CAV has its own slot for the whole episode (slot k = the k-th
CAV). In a ``demand`` scenario CAVs enter and leave: a CAV that enters takes
the first free slot (CAVs in order of entry), keeps it until it leaves, and
its slot stays pointed at it for the step it arrives (so the reward sees the
arrival) and is free from the next step on. A refilled slot is flagged in
``Transition.slot_start``: the policy starts that slot's recurrent state
afresh. An empty slot points at a vehicle that is not on the road, so every
consumer of ``cav_index`` sees it dead (``alive`` False) without knowing
about slots. With ``cav_slots = "every"`` (the default) there is a slot for
every CAV of the episode, so none ever waits for one; under a cap, CAVs that
find no free slot (more than ``cav_slots`` at once) drive themselves meanwhile
(no command, :mod:`diacc.sim.backends.base`) and are counted in
:attr:`BottleneckEnv.unserved_cavs`.
PettingZoo names agents by CAV, not slot: ``possible_agents`` are
``cav_0 .. cav_{K-1}`` for the K CAVs of the episode in order of entry, and
``agents`` are those on the road and in a slot now, after a step of either API.

Two APIs share the same code path: the PettingZoo dict API (``reset`` /
``step``) for users and API tests, and the array API (:meth:`reset_arrays` /
:meth:`step_arrays`) without per-agent dicts. Both adapt the one step function
of :mod:`diacc.envs.batch` with a batch of one env; the vector envs of training
(:mod:`diacc.envs.vector`) adapt the same function with many.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper

from diacc.config import EnvConfig, resolve_road
from diacc.envs.actions import ACTION_NAMES
from diacc.envs.api_checks import EnvCallError, check_action_array, check_actions, check_seed
from diacc.envs.batch import EnvBatch, Simulators, decide
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.reward import RewardError, temperature
from diacc.envs.spaces import agent_observation, check_format, observation_space, state_space
from diacc.envs.step import Transition, score
from diacc.errors import DiaccError
from diacc.sim.backends.base import Backend, make_backend
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState

__all__ = [
    "ACTION_NAMES",
    "AnnealTemperature",
    "BottleneckEnv",
    "EnvCallError",
    "EnvConfig",
    "RenderModeError",
    "decide",
]

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


def _env_zero(name: str, doc: str, convert=None) -> property:
    """A read-only property: env 0's row of ``EpisodeState`` field ``name`` (diacc.envs.batch)."""

    def get(env: BottleneckEnv):
        value = getattr(env.batch.state, name)[0]
        return value if convert is None else convert(value)

    return property(get, doc=doc)


class RenderModeError(DiaccError, ValueError):
    """A render mode this environment cannot honour here; one line."""


class BottleneckEnv(ParallelEnv):
    """CAVs crossing a highway bottleneck among HDVs (see module docstring).

    Every agent's reward is the team reward at temperature :attr:`tau` (module
    docstring; :class:`AnnealTemperature` anneals it over a training run).
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
        one of ``config.backend`` on ``config``'s road (:func:`~diacc.config.resolve_road`).
        ``render_mode``: ``None``, ``"rgb_array"`` (:meth:`render` returns a frame) or
        ``"human"`` (a window, refreshed every step; refused without a display).
        ``observation_format``: ``"dict"`` or ``"flat"`` (:mod:`diacc.envs.spaces`)."""
        self.config = config or EnvConfig()
        self.render_mode = check_render_mode(render_mode)
        self.observation_format = check_format(observation_format)
        if backend is None:
            backend = make_backend(self.config.backend, resolve_road(self.config), self.config.sim)
        self.backend: Backend = backend
        self.road: Map = backend.road
        #: The step function this env adapts: a batch of one (:mod:`diacc.envs.batch`).
        self.batch = EnvBatch(self.config, Simulators([backend]))
        self.n_cavs = self.config.scenario.n_slots  # C agent slots
        self.possible_agents = [f"cav_{k}" for k in range(self.config.scenario.n_cavs)]
        self.agents: list[str] = []
        #: Softmin temperature of the team reward of the next steps (module docstring).
        self.tau: float = self.config.reward.tau_init
        self.state_: TrafficState | None = None
        #: The last step as the batch of one it is (:class:`~diacc.envs.step.Transition`):
        #: what evaluation records, without unbatching and rebatching it.
        self.transition: Transition | None = None
        self._viewer = None  # diacc.sim.viewer.Viewer, made by the first render()
        self._window = None  # diacc.sim.viewer.Window of render_mode "human"
        self._recorder: EpisodeRecorder | None = None  # episode metrics of the dict API
        self._seed: int | None = None
        self._over = False  # the episode has terminated or been truncated
        # Spaces are the same for every agent: built once, returned as the same object.
        spec = self.batch.builder.spec()
        self._dict_space = observation_space(spec, "dict")
        self._observation_space = observation_space(spec, self.observation_format)
        self._action_space = gymnasium.spaces.Discrete(len(ACTION_NAMES))
        self.state_space = state_space(spec)

    # ------------------------------------------------------------------ batched API
    def reset_arrays(self, seed: int | None = None) -> tuple[ActorObs, CriticState]:
        """Start an episode; returns observations for all CAV slots and the critic state."""
        seed = check_seed(seed)
        self._over = False
        if seed is None:
            seed = 0 if self._seed is None else self._seed + 1
        self._seed = seed = check_seed(seed)
        self.batch.reset([0], [seed])
        self.state_ = self.batch.state.traffic.env(0)
        self.transition = None
        self.agents = self._live_agents(self.state_)
        self._recorder = None  # the dict API's reset() starts one; the batched API needs none
        actor, critic = self.batch.observe()
        return actor.unbatched(0), critic.unbatched(0)

    def step_arrays(self, actions: np.ndarray) -> Transition:
        """Advance one decision step with proposed actions (C,) for every CAV slot; the
        step in env 0's view ((C,) arrays), with its team reward (``reward``)."""
        if self.state_ is None or self._over:
            what = "has ended" if self._over else "has not started"
            raise EnvCallError(f"the episode {what}; call reset() before step()")
        out = self.batch.step(check_action_array(actions, self.n_cavs)[None])
        if out.crashed[0]:
            raise self.batch.sims.errors[0]
        self.transition = score(out, self.tau, self.config.reward)
        result = self.transition.unbatched(0)  # the PettingZoo edge: the env axis goes here
        self.state_ = result.state
        self._over = result.terminated or result.truncated
        # Both APIs keep ``agents`` current: a policy on the array API that reads
        # PettingZoo dicts (agent_observations) must see the CAVs on the road now.
        self.agents = [] if self._over else self._live_agents(result.state)
        return result

    # The episode's slots and memories: env 0 of the batch's EpisodeState (module
    # docstring, "Agent slots").
    cav_index = _env_zero(
        "cav_index", "(C,) vehicle each agent slot points at (empty: one off the road)."
    )
    slot_vehicle = _env_zero("slot_vehicle", "(C,) occupant of each agent slot, -1 none.")
    slot_start = _env_zero(
        "slot_start", "(C,) bool: a new CAV took the slot at the last step or reset."
    )
    cav_ordinal = _env_zero("cav_ordinal", "(V,) k of the k-th CAV (PettingZoo agent ``cav_k``).")
    action_memory = _env_zero(
        "action_memory", "(C, 2) proposed and refined action of the last step."
    )
    last_refined = _env_zero("last_refined", "(V,) refined action each vehicle executed last.")
    unserved_cavs = _env_zero(
        "unserved_cavs", "CAVs on the road without a slot (they drive themselves).", int
    )
    steps = _env_zero("steps", "Decision steps of the episode so far.", int)

    @property
    def traffic(self) -> TrafficState:
        """The current state as the batch of one the env steps ((1, V) arrays; :attr:`state_`
        is a copy of it)."""
        return self.batch.state.traffic

    @property
    def neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, K) neighbour indices and mask of the current state (the observations')."""
        nbr, mask = self.batch.builder.neighbours
        return nbr[0], mask[0]

    def _live_agents(self, state: TrafficState) -> list[str]:
        """PettingZoo names of the CAVs on the road that hold a slot."""
        live = self.slot_vehicle[self.slot_vehicle >= 0]
        live = np.sort(live[state.active[0, live]])  # state: a batch of one env
        return [f"cav_{k}" for k in self.cav_ordinal[live]]

    # ------------------------------------------------------------------ PettingZoo API
    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        """One agent's observation space (:mod:`diacc.envs.spaces`; no reset needed)."""
        return self._observation_space

    def action_space(self, agent: str) -> gymnasium.spaces.Discrete:
        return self._action_space

    def agent_slots(self) -> dict[str, int]:
        """Slot of each agent (CAV) that holds one now: PettingZoo names -> array rows."""
        held = np.flatnonzero(self.slot_vehicle >= 0)
        return {f"cav_{self.cav_ordinal[self.slot_vehicle[i]]}": int(i) for i in held}

    def agent_observations(self, actor_obs: ActorObs) -> dict[str, dict | np.ndarray]:
        """PettingZoo observations of :attr:`agents` from the array API's ``actor_obs`` of
        the current step (what the evaluator hands a user's dict-API policy)."""
        slots = self.agent_slots()
        return {a: self._agent_obs(actor_obs, slots[a]) for a in self.agents}

    def reset(self, seed: int | None = None, options: dict | None = None):
        actor_obs, _ = self.reset_arrays(seed)
        self._recorder = EpisodeRecorder(
            self.road, self.config.events, self.config.scenario.warmup_s
        )
        self._recorder.record(self.traffic)
        observations = self.agent_observations(actor_obs)
        if self.render_mode == "human":
            self.render()
        return observations, {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        if self._over and isinstance(actions, Mapping) and not actions:
            # No agent is left to act: nothing happens (SuperSuit's black_death steps
            # once more with no actions to see every agent done, then resets).
            return {}, {}, {}, {}, {}
        if self.state_ is None or self._over:  # before the actions: they name no live agent
            self.step_arrays(np.zeros(self.n_cavs, np.int64))
        actions = check_actions(actions, self.agents, self.possible_agents)
        index = self.agent_slots()
        batch = np.zeros(self.n_cavs, np.int64)
        for agent, action in actions.items():
            batch[index[agent]] = action
        acting = list(self.agents)  # step_arrays moves agents on to the next step's
        out = self.step_arrays(batch)
        if self._recorder is not None:
            self._recorder.record(self.transition.state, psar=self.transition.psar)
        ended = out.terminated or out.truncated
        # CAVs that took a slot in this step join (PettingZoo lets agents appear).
        index.update(self.agent_slots())
        joining = [] if ended else [a for a in self._live_agents(out.state) if a not in acting]
        observations, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for agent in acting + joining:
            i = index[agent]
            observations[agent] = self._agent_obs(out.actor_obs, i)
            rewards[agent] = out.reward
            terms[agent] = out.terminated or not out.actor_obs.alive[i]
            truncs[agent] = out.truncated
            infos[agent] = {
                "refined_action": int(out.refined_action[i]),
                "psar_rule": int(out.psar_rule[i]),
                "collisions": out.state.collisions.copy(),
                "arrivals": out.state.arrivals.copy(),
            }
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
        critic = self.batch.builder.critic().unbatched(0)
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


class AnnealTemperature(BaseParallelWrapper):
    """A :class:`BottleneckEnv` whose team reward anneals over a training run of its own.

    The env emits R at the temperature it is given; the schedule belongs to
    whoever trains. A trainer of another library (TorchRL, SB3, RLlib: the
    examples) knows its budget but not the env, so it wraps the env in this,
    under its own wrappers::

        env = AnnealTemperature(diacc.parallel_env(...), total_steps=budget)

    Before each step through it (PettingZoo's ``step`` or ``step_arrays``) the
    env's :attr:`~BottleneckEnv.tau` is :func:`~diacc.envs.reward.temperature`
    at :attr:`steps`, the env steps taken through it so far, of a run of
    ``total_steps`` env steps: the schedule of ``diacc train`` for a run on this
    env alone (``TrainConfig().total_steps`` is ``diacc train``'s default budget).
    A call that simulates nothing (``step({})`` after the episode's end) or
    raises does not count.
    """

    env: BottleneckEnv

    def __init__(self, env: BottleneckEnv, total_steps: int) -> None:
        if isinstance(total_steps, bool) or not isinstance(total_steps, (int, np.integer)):
            raise RewardError(f"total_steps must be a whole number, got {total_steps!r}")
        if total_steps <= 0:
            raise RewardError(f"total_steps must be positive, got {total_steps}")
        super().__init__(env)
        self.total_steps = int(total_steps)
        self.steps = 0  # env steps taken: the schedule's t

    def step(self, actions):
        return self._annealed(self.env.step, actions)

    def step_arrays(self, actions: np.ndarray) -> Transition:
        return self._annealed(self.env.step_arrays, actions)

    def _annealed(self, step, actions):
        self.env.tau = temperature(self.steps, self.total_steps, self.env.config.reward)
        before = self.env.transition
        out = step(actions)
        if self.env.transition is not before:  # the env simulated a step
            self.steps += 1
        return out


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

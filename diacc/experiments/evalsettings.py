"""What an evaluation overrides of a policy's own settings: :class:`EvalSettings`.

One record for every evaluation command (``diacc eval``, ``scorecard``, the
benches), so that every policy of a comparison meets the same simulator, PSAR,
agent slots and seed stream; checked when built, recorded in ``meta.json``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from diacc.config import (
    BACKENDS,
    FULL_BRAKE_MODES,
    HIGHWAY_MERGES,
    HORIZON_MODES,
    MAX_EPISODE_STEPS,
    ON_COLLISION,
    STYLE_PRESETS,
    PSARConfig,
    SimConfig,
)
from diacc.experiments.grid import DEFAULT_STREAM, SEED_STREAMS
from diacc.experiments.userpolicy import DEFAULT_TIMEOUT_S
from diacc.fields import MAX_VEHICLES, FieldError, check_fields, one_of, ranged
from diacc.sim.scenario import EVERY_CAV, Demand, Scenario
from diacc.sim.settings import check_merges_backend

#: ``EvalSettings.agent_slots`` besides a cap (an int): one slot for every CAV, or the
#: policy's own ``cav_slots`` (a checkpoint's from its training).
AGENT_SLOTS = (EVERY_CAV, "own")


@dataclass(frozen=True)
class EvalSettings:
    """Evaluation-wide overrides of a policy's own simulation settings (None = keep).

    Checked as every config section is (:func:`diacc.fields.check_fields`: a value
    out of its choices or range is a one-line :class:`~diacc.config.ConfigError`
    naming the field), when built, before any episode runs.
    """

    backend: str = one_of("highway", BACKENDS)
    episode_steps: int | None = ranged(
        None, 1, MAX_EPISODE_STEPS, why="an episode's steps are stored and replayed"
    )
    style_preset: str | None = one_of(None, tuple(STYLE_PRESETS))
    #: PSAR horizon of every policy with PSAR (baselines and checkpoints alike), so that a
    #: comparison's rules and learners are filtered by the same PSAR.
    psar_horizon: str | None = one_of(None, HORIZON_MODES)
    #: PSAR's ``full_brake`` of every policy with PSAR (:class:`~diacc.config.PSARConfig`).
    psar_full_brake: str | None = one_of(None, FULL_BRAKE_MODES)
    #: How the highway backend's human drivers leave an ending lane (``SimConfig``'s).
    highway_merges: str | None = one_of(None, HIGHWAY_MERGES)
    #: Agent slots of a demand cell: ``every`` CAV a slot (the default; no CAV drives
    #: itself, :meth:`~diacc.sim.scenario.Demand.with_a_slot_per_cav`), a cap N on the
    #: CAVs driven at once, or the policy's ``own`` ``cav_slots``; with a cap a CAV that
    #: finds every slot taken drives itself. Releases slot every CAV.
    agent_slots: int | str = EVERY_CAV
    #: What a collision does (:data:`~diacc.config.ON_COLLISION`): evaluation ``remove``\ s
    #: the vehicles that collided and runs on to ``episode_steps``, so that a crash never
    #: shortens the episode its delay and throughput average over; ``end`` is training's
    #: rule (and every result recorded before 2026-12-06).
    on_collision: str = one_of("remove", ON_COLLISION)
    #: Seed stream of the episodes (:data:`~diacc.experiments.grid.SEED_STREAMS`):
    #: ``validation`` to choose on, ``test`` to report.
    stream: str = one_of(DEFAULT_STREAM, SEED_STREAMS)
    #: Longest a user's controller may take in one ``act`` or ``reset`` call (s; 0: no
    #: limit); changes no result, so ``meta.json`` does not record it.
    controller_timeout_s: float = ranged(DEFAULT_TIMEOUT_S, 0)

    def __post_init__(self) -> None:
        check_fields(self)
        check_merges_backend(self.backend, self.highway_merges)
        slots = self.agent_slots
        if slots not in AGENT_SLOTS and (
            isinstance(slots, bool) or not isinstance(slots, int) or not 1 <= slots <= MAX_VEHICLES
        ):
            raise FieldError(
                "agent_slots",
                f"must be one of {', '.join(AGENT_SLOTS)} or an integer in [1, {MAX_VEHICLES}], "
                f"got {slots!r}",
            )

    def apply_slots(self, scenario: Scenario) -> Scenario:
        """A demand ``scenario`` with these agent slots (a release is left as it is)."""
        if not isinstance(scenario, Demand) or self.agent_slots == "own":
            return scenario
        return dataclasses.replace(scenario, cav_slots=self.agent_slots)

    def apply(self, sim: SimConfig) -> SimConfig:
        changes = {}
        if self.episode_steps is not None:
            changes["episode_steps"] = self.episode_steps
        if self.style_preset is not None:
            changes["style_preset"] = self.style_preset
        if self.highway_merges is not None:
            changes["highway_merges"] = self.highway_merges
        return dataclasses.replace(sim, on_collision=self.on_collision, **changes)

    def apply_psar(self, psar: PSARConfig) -> PSARConfig:
        changes = {"horizon": self.psar_horizon, "full_brake": self.psar_full_brake}
        return dataclasses.replace(psar, **{k: v for k, v in changes.items() if v is not None})

    def describe(self) -> dict:
        """What an evaluation's ``meta.json`` records of these settings (and checks on reuse)."""
        settings = {
            "episode_steps": self.episode_steps,
            "style_preset": self.style_preset,
            "stream": self.stream,
        }
        if self.psar_horizon is not None:  # absent otherwise: older results stay reusable
            settings["psar_horizon"] = self.psar_horizon
        if self.psar_full_brake is not None:
            settings["psar_full_brake"] = self.psar_full_brake
        if self.highway_merges is not None:
            settings["highway_merges"] = self.highway_merges
        if self.agent_slots != "own":
            settings["agent_slots"] = self.agent_slots
        settings["on_collision"] = self.on_collision
        return {"backend": self.backend, "settings": settings}

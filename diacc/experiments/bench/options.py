"""``diacc bench``'s shared options, checked as every config section is.

The step counts, episode counts and demand settings that several benchmarks read
are fields of :class:`BenchOptions`, with their ranges next to them and checked by
:func:`diacc.fields.check_fields` when it is built from the command line, with the
relations between options (which flags need which mode); one one-line
:class:`~diacc.config.ConfigError` naming the flag, before anything runs.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

from diacc.config import MAX_EPISODE_STEPS, ConfigError
from diacc.experiments.evaluate import MAX_EPISODES
from diacc.fields import MAX_INFLOW_VPH, FieldError, check_fields, one_of, ranged
from diacc.sim.scenario import SCENARIO_KINDS

_STEPS_WHY = "an episode's steps are stored"
_TIMING_WHY = "timed steps run one after another"


@dataclass(frozen=True)
class BenchOptions:
    """The options of ``diacc bench`` that more than one benchmark reads (None: each
    benchmark's default); field names are the flags' (``episode_steps``:
    ``--episode-steps``; ``steps``: the hidden former ``--steps``)."""

    safety: bool = False
    headway: bool = False
    headroom: bool = False
    fidelity: bool = False
    scenario: str = one_of("release", SCENARIO_KINDS)
    episodes: int | None = ranged(None, 1, MAX_EPISODES, why="each is seconds of simulation")
    episode_steps: int | None = ranged(None, 1, MAX_EPISODE_STEPS, why=_STEPS_WHY)
    timing_steps: int | None = ranged(None, 1, MAX_EPISODE_STEPS, why=_TIMING_WHY)
    steps: int | None = ranged(None, 1, MAX_EPISODE_STEPS, why=_TIMING_WHY)
    # vehicles per hour of --headroom --scenario demand (one) or --fidelity (several)
    inflow: tuple[float, ...] | None = ranged(
        None, 0, MAX_INFLOW_VPH, open_low=True, why="more than 4 lanes carry"
    )
    demand_s: float | None = ranged(None, 0, open_low=True)
    warmup_s: float | None = ranged(None, 0)
    agent: tuple[str, ...] = ()
    references: str | None = None
    highway_merges: str | None = None

    def __post_init__(self) -> None:
        try:
            check_fields(self)
        except FieldError as exc:  # name the flag the user typed
            flag = "--" + exc.key.split("[")[0].replace("_", "-")
            raise ConfigError(f"{flag} {exc.problem}") from None
        demand_flags = {
            "--inflow": self.inflow,
            "--demand-s": self.demand_s,
            "--warmup-s": self.warmup_s,
        }
        given = [flag for flag, value in demand_flags.items() if value is not None]
        given += ["--scenario demand"] * (self.scenario == "demand")
        if self.fidelity and self.scenario == "release":
            given = []  # --fidelity runs the demand scenario: its flags apply
        if given and not (self.headroom and self.scenario == "demand"):
            raise ConfigError(f"{given[0]} needs --headroom with --scenario demand or --fidelity")
        if self.highway_merges is not None and not self.fidelity:
            raise ConfigError("--highway-merges needs --fidelity")
        if (self.agent or self.references) and not self.headroom:
            raise ConfigError(f"{'--agent' if self.agent else '--references'} needs --headroom")
        if self.headroom and self.scenario == "demand" and len(self.inflow or ()) != 1:
            raise ConfigError("--scenario demand needs --inflow (one value, vehicles per hour)")

    @classmethod
    def of(cls, args: argparse.Namespace) -> BenchOptions:
        """The options of parsed ``diacc bench`` arguments, checked."""
        values = {f.name: getattr(args, f.name, None) for f in dataclasses.fields(cls)}
        values["steps"] = getattr(args, "legacy_steps", None)
        values["inflow"] = None if args.inflow is None else tuple(args.inflow)
        values["agent"] = tuple(args.agent or ())
        values["scenario"] = args.scenario or "release"
        for name in ("safety", "headway", "headroom", "fidelity"):
            values[name] = bool(values[name])
        return cls(**values)

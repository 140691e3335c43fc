"""``diacc bench --safety``: can scripted CAVs cross the bottleneck without collisions?

Scripted policies (:class:`~diacc.experiments.policies.ScriptedPolicy`: always
``remain``, always ``accelerate``, uniform ``random``, the ``heuristic``
that accelerates and leaves an ending lane early, and ``late-merge``, which
leaves it only 150 m before its end) drive the CAVs of the
paper's training scenario (N = 25, rho = 0.4, D1) with and without PSAR, on
every map and backend, through the same episode driver as evaluation
(:func:`diacc.experiments.evaluate.run_episode`). A policy that knows nothing about
traffic is the hardest test of the safety layer: whatever it proposes, PSAR
should keep it out of collisions, and HDVs should never collide with each
other. Per (backend, map, policy) it prints the collision-free share of
episodes, the number of HDV-HDV collision pairs, the mean speed of all
vehicles, p(SCE) and the arrived fraction. The HDV style preset and the
episode length are the evaluation's (:class:`~diacc.experiments.policies.EvalSettings`,
``--style-preset`` and ``--episode-steps``), so the congested ``paper-congestion``
runs with 330-step episodes are benchmarked too.

Target (issue "Collision-free bottleneck driving"): with PSAR, ``remain``,
``accelerate``, ``heuristic`` and ``late-merge`` collision-free in >= 95 % of episodes on every
map and both backends, and 0 HDV-HDV collisions. Without PSAR collisions are
expected.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from diacc.config import BACKENDS, PSARConfig, SimConfig
from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import SCRIPTED, EvalSettings, ScriptedPolicy
from diacc.sim.maps import available_maps

#: Policies of the benchmark: each script with PSAR, then without.
POLICIES = tuple(SCRIPTED) + tuple(f"{name}-nopsar" for name in SCRIPTED)
#: Target collision-free share for these policies (all with PSAR).
TARGET_COLLISION_FREE = 0.95
TARGET_POLICIES = ("remain", "accelerate", "heuristic", "late-merge")


@dataclass
class SafetyRow:
    """Aggregate of one (backend, map, policy) over its episodes."""

    backend: str
    map: str
    policy: str
    episodes: int
    collision_free: float  # share of episodes without any collision
    hdv_hdv_collisions: int  # collision pairs of two HDVs, summed over episodes
    mean_speed_mps: float  # mean over episodes of the episode mean speed
    p_sce: float  # mean over episodes
    arrived_fraction: float  # mean over episodes

    @property
    def meets_target(self) -> bool | None:
        """None where the target does not apply (random, no PSAR)."""
        if self.policy not in TARGET_POLICIES:
            return None
        return self.collision_free >= TARGET_COLLISION_FREE and self.hdv_hdv_collisions == 0


def measure(
    settings: EvalSettings,
    map_name: str,
    policy_name: str,
    episodes: int,
    horizon: str | None = None,
) -> SafetyRow:
    """Run ``episodes`` seeded episodes of one scripted policy; seeds of the legacy
    evaluation stream (those of its committed results).

    ``horizon``: PSAR's (:attr:`~diacc.config.PSARConfig.horizon`; None keeps the default).
    """
    policy = ScriptedPolicy(policy_name)
    if horizon is not None:
        psar_cfg = dataclasses.replace(policy.base.psar, horizon=horizon)
        policy.base = dataclasses.replace(policy.base, psar=psar_cfg)
    cell = Cell(map_name, 25, 0.4, "D1")
    backend = settings.backend
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    try:
        rows = [run_episode(driver, cell, k, "legacy").row for k in range(episodes)]
    finally:
        driver.close()
    return SafetyRow(
        backend=backend,
        map=map_name,
        policy=policy_name,
        episodes=episodes,
        collision_free=float(np.mean([r["collision"] == 0 for r in rows])),
        hdv_hdv_collisions=int(sum(r["n_hdv_collisions"] for r in rows)),
        mean_speed_mps=float(np.mean([r["mean_speed_mps"] for r in rows])),
        p_sce=float(np.mean([r["p_sce"] for r in rows])),
        arrived_fraction=float(np.mean([r["arrived_fraction"] for r in rows])),
    )


def run(
    backends: tuple[str, ...] = BACKENDS,
    maps: tuple[str, ...] | None = None,
    policies: tuple[str, ...] = POLICIES,
    episodes: int = 20,
    style_preset: str | None = None,
    episode_steps: int | None = None,
    horizon: str | None = None,
) -> list[SafetyRow]:
    """Measure every combination and print one Markdown table; returns the rows.

    ``style_preset`` / ``episode_steps`` / ``horizon`` (PSAR's): None keeps the
    defaults of :class:`~diacc.config.SimConfig` / :class:`~diacc.config.PSARConfig`.
    """
    maps = tuple(maps or available_maps())
    sim = EvalSettings(style_preset=style_preset, episode_steps=episode_steps).apply(SimConfig())
    print(
        f"safety benchmark: N = 25, rho = 0.4, D1, style preset {sim.style_preset}, "
        f"{sim.episode_steps}-step episodes, PSAR horizon {horizon or PSARConfig().horizon}, "
        f"{episodes} seeded episodes per row "
        f"(seeds of `diacc eval --stream legacy`)"
    )
    print(
        "| backend | map | policy | collision-free | HDV-HDV collisions | mean speed m/s "
        "| p(SCE) | arrived | target |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    out = []
    start = time.perf_counter()
    for backend in backends:
        for map_name in maps:
            for policy_name in policies:
                settings = EvalSettings(backend, episode_steps, style_preset)
                row = measure(settings, map_name, policy_name, episodes, horizon)
                out.append(row)
                target = {None: "", True: "met", False: "**missed**"}[row.meets_target]
                print(
                    f"| {backend} | {map_name} | {policy_name} | {row.collision_free:.0%} "
                    f"| {row.hdv_hdv_collisions} | {row.mean_speed_mps:.2f} | {row.p_sce:.0%} "
                    f"| {row.arrived_fraction:.0%} | {target} |",
                    flush=True,
                )
    checked = [r.meets_target for r in out if r.meets_target is not None]
    print(
        f"target met in {sum(checked)} of {len(checked)} rows ({time.perf_counter() - start:.0f} s)"
    )
    return out

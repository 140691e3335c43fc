"""What the ``diacc`` command and the tutorials print: rounded numbers, "n/a", configs.

Metrics are ``nan`` where a quantity does not apply (CAV speed without CAVs,
a segment kind the map lacks, PSAR rates without PSAR decisions); users see
"n/a" for those, or nothing, never ``nan``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from diacc.envs.metrics import EpisodeMetrics

NA = "n/a"


def fmt(value: float | int | None, digits: int = 2, unit: str = "", percent: bool = False) -> str:
    """``value`` rounded to ``digits`` (x100 and "%" if ``percent``), or "n/a" if undefined."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return NA
    if percent:
        return f"{100.0 * value:.{digits}f} %"
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value}{' ' + unit if unit else ''}"
    return f"{value:.{digits}f}{' ' + unit if unit else ''}"


def plural(n: int, noun: str) -> str:
    """``1 episode``, ``3 episodes``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def metric_lines(metrics: EpisodeMetrics, kinds: tuple[str, ...]) -> list[tuple[str, str]]:
    """(label, value) lines of one episode's metrics, leaving out what does not apply.

    ``kinds`` are the segment kinds of the map: speeds on kinds the map lacks
    are omitted, as are CAV speeds without CAVs and PSAR rates without PSAR.
    """
    lines = [
        ("mean speed", f"{fmt(metrics.mean_speed_mps)} ± {fmt(metrics.std_speed_mps)} m/s"),
        ("mean HDV speed", fmt(metrics.mean_hdv_speed_mps, unit="m/s")),
    ]
    if math.isfinite(metrics.mean_cav_speed_mps):
        lines.append(("mean CAV speed", fmt(metrics.mean_cav_speed_mps, unit="m/s")))
    lines += [
        (f"speed on {kind}", fmt(metrics.mean_speed_by_kind_mps[kind], unit="m/s"))
        for kind in kinds
    ]
    lines += [
        ("p(WE) waiting events", fmt(metrics.p_we, 1, percent=True)),
        ("p(SCE) safety-critical", fmt(metrics.p_sce, 1, percent=True)),
        ("collisions (pairs)", str(metrics.n_collisions)),
        ("arrived", fmt(metrics.arrived_fraction, 1, percent=True)),
        (
            "mean travel time",
            fmt(metrics.mean_travel_time_s, 1, unit="s")
            if math.isfinite(metrics.mean_travel_time_s)
            else f"{NA} (no vehicle arrived)",
        ),
        ("vehicles seen", str(metrics.n_vehicles)),
        ("steps", str(metrics.episode_steps)),
    ]
    if metrics.psar_decisions:
        lines += [
            (f"PSAR {name} rate", fmt(rate, 1, percent=True))
            for name, rate in metrics.psar_fire_rate.items()
        ]
    return lines


def print_lines(lines: list[tuple[str, str]], indent: int = 2) -> None:
    """Aligned ``label: value`` lines."""
    width = max(len(label) for label, _ in lines)
    for label, value in lines:
        print(f"{' ' * indent}{label:<{width}} : {value}")


def _flat(config: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_flat(value, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = value
    return out


def _flat_defaults(config: Any, default: Any, prefix: str = "") -> dict[str, Any]:
    """The default of every key :func:`_flat` gives ``config``: ``default``'s value where
    ``default`` has the field, else that of the section's own type.

    A section may be of another type than its default (``--set env.scenario.kind=demand``
    makes the default release a :class:`~diacc.sim.scenario.Demand`): its keys of the
    default's type compare with the default (``kind``), its own keys (``inflow_vph``) with
    its type's defaults, so that every key has a default to compare with.
    """
    out: dict[str, Any] = {}
    own = type(config)()
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        base = getattr(default, f.name) if hasattr(default, f.name) else getattr(own, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_flat_defaults(value, base, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = base
    return out


def config_table(config: Any, title: str):
    """A rich table of a config: every top-level field, and nested fields that differ
    from their defaults (the full tree is in the run's ``config.json``)."""
    from rich.table import Table

    table = Table(
        caption=f"{title}; nested sections: changed keys only",
        caption_justify="left",
        header_style="bold",
    )
    table.add_column("key")
    table.add_column("value")
    table.add_column("default if changed", style="dim")
    default = _flat_defaults(config, type(config)())
    if "run_dir" in default:  # its default follows the config's variant, backend, map, seed
        from diacc.config import default_run_dir

        default["run_dir"] = default_run_dir(config)
    for key, value in _flat(config).items():
        changed = value != default[key]
        if "." in key and not changed:
            continue
        table.add_row(
            f"[bold]{key}[/bold]" if changed else key,
            repr(value) if isinstance(value, str) else str(value),
            "" if not changed else str(default[key]),
        )
    return table


def print_config(config: Any, heading: str, title: str) -> None:
    """Print ``heading`` and :func:`config_table` with rich (plain when not on a terminal)."""
    from rich.console import Console

    console = Console()
    console.print(heading, highlight=False)
    console.print(config_table(config, title))


class TrainProgress:
    """The training bar: one throughput, the whole run's ETA, and how the agents drive.

    The bar counts environment steps (one step of one env) over the whole
    run, so its rate is env steps per wall-clock second *including* the PPO
    updates, and its ETA is that of the run (``--steps``), even when the run
    stops early. The postfix is the team reward of the last update and, over
    the last :attr:`window` finished episodes, the mean speed and the share
    of episodes that ended in a collision.
    """

    window = 20

    def __init__(self, total_steps: int, done_steps: int, desc: str, enabled: bool) -> None:
        from collections import deque

        from tqdm import tqdm

        self._episodes: deque[dict] = deque(maxlen=self.window)
        self.bar = tqdm(
            total=total_steps,
            initial=done_steps,
            unit=" env step",
            unit_scale=True,
            disable=not enabled,
            desc=desc,
            bar_format="{desc}: {percentage:3.0f}%|{bar:20}| {n_fmt}/{total_fmt} "
            "[{elapsed}<{remaining}, {rate_fmt}]{postfix}",
        )

    def update(self, steps: int, team_reward: float, episodes: list[dict]) -> None:
        """Advance by ``steps`` after an update whose rollout finished ``episodes``
        (dicts with ``mean_speed_mps`` and ``n_collisions``)."""
        self._episodes.extend(episodes)
        self.bar.set_postfix_str(self.postfix(team_reward), refresh=False)
        self.bar.update(steps)

    def postfix(self, team_reward: float) -> str:
        """``R=0.41 | last 20 ep: 18.2 m/s, collisions 5 %`` (n/a before any episode ended)."""
        text = f"R={team_reward:.2f}"
        if not self._episodes:
            return f"{text} | no episode finished yet"
        speeds = [ep["mean_speed_mps"] for ep in self._episodes]
        finite = [s for s in speeds if math.isfinite(s)]
        speed = sum(finite) / len(finite) if finite else float("nan")
        crashed = sum(ep["n_collisions"] > 0 for ep in self._episodes) / len(self._episodes)
        return (
            f"{text} | last {plural(len(self._episodes), 'ep')}: {fmt(speed, 1, 'm/s')}, "
            f"collisions {fmt(crashed, 0, percent=True)}"
        )

    def close(self) -> None:
        self.bar.close()

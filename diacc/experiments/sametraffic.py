"""Only the same traffic is paired or pooled: the check ``diacc table`` and ``plot flow``
make before they compare episodes (issue 61).

A table pairs the episodes of its columns in a cell by episode seed, and pools
each column's episodes of a cell into one entry; the flow figure pools a
series' episodes at one inflow into one point, beside the other series'.
Both mean the *same* traffic: episodes of other episode lengths, presets,
highway merge models, seed streams or demand timings in one cell would print
changes, rankings and intervals of numbers that measure different things.
:func:`check_same_traffic` refuses that with one line naming the two columns,
the cell and what differs, and refuses an episode that appears twice in a
column (a duplicated row would be counted twice).

What an episode's traffic is (:func:`traffic_of`): its cell (map, N, CAV
share, style mix, inflow) and demand timing, the HDV style preset, the seed
stream, the episode length asked for (``meta.json``'s settings; absent or
``null``: the policy's own, which matches any), and on the highway backend
the merge model (``highway_merges``, same rule). Per cell and episode number
the seed must agree too. The backend is not part of it: columns on both
backends share a table, and its changes pair within one backend.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from diacc.experiments.grid import Cell
from diacc.experiments.results_files import EvaluationError, cell_id

#: A column to check: (its name, its ``meta.json``, its ``episodes.csv`` rows).
Column = tuple[str, Mapping, list[dict[str, str]]]
#: Row key naming the training run of a row where a column pools several runs
#: (:data:`diacc.experiments.report.collect.TRAINING_RUN`): episodes repeat across runs.
_RUN = "training_run"
#: Row fields of an episode's traffic: cell keys and timing (numbers), preset, stream.
_NUMBER_FIELDS = ("n_vehicles", "cav_penetration", "inflow_vph", "demand_s", "warmup_s")
_TEXT_FIELDS = ("map", "style_mix", "style_preset")


class TrafficMismatch(EvaluationError):
    """Episodes of different traffic would be paired or pooled; one line."""


def traffic_of(meta: Mapping, row: Mapping[str, str]) -> dict[str, object]:
    """What makes the traffic of one episode row (module docstring); None: unknown, any."""
    settings = meta.get("settings") if isinstance(meta.get("settings"), Mapping) else {}
    traffic: dict[str, object] = {k: row.get(k) or None for k in _TEXT_FIELDS}
    traffic.update({k: float(row.get(k) or 0.0) for k in _NUMBER_FIELDS})
    traffic["stream"] = row.get("stream") or "legacy"  # results before streams: legacy seeds
    traffic["episode length"] = settings.get("episode_steps")
    highway = (row.get("backend") or meta.get("backend")) == "highway"
    traffic["highway merge model"] = settings.get("highway_merges") if highway else None
    return traffic


def row_cell(row: Mapping[str, str]) -> str:
    """The key of an episode row's cell (``train-25_N25_rho0.40_D1``): what a table pairs in."""
    return Cell(*cell_id(row)).key


def check_same_traffic(
    columns: list[Column], cell_of: Callable[[Mapping[str, str]], str] = row_cell
) -> None:
    """One-line :class:`TrafficMismatch` unless every episode of a cell (``cell_of(row)``,
    what is paired or pooled) is of the same traffic in every column, with the same seed
    per episode number, and no column holds an episode twice (columns of one name pool
    into one: a flow series from several files)."""
    seen: dict[tuple[str, str], tuple[object, str]] = {}  # (cell, field) -> (value, column)
    episodes: dict[str, set[tuple]] = {}  # column -> (cell, backend, run, episode) found
    for name, meta, rows in columns:
        for row in rows:
            cell, episode = cell_of(row), row.get("episode")
            key = (row_cell(row), row.get("backend"), row.get(_RUN), episode)
            if key in episodes.setdefault(name, set()):
                raise TrafficMismatch(
                    f"{name} holds episode {episode} of {key[0]} twice; a duplicated row would "
                    "be counted twice (remove it, or re-run `diacc eval` into a fresh --out)"
                )
            episodes[name].add(key)
            found = traffic_of(meta, row)
            if row.get("seed"):
                found[f"seed of episode {episode}"] = int(float(row["seed"]))
            for field, value in found.items():
                _agree(seen, cell, field, value, name)


def _agree(seen: dict, cell: str, field: str, value: object, column: str) -> None:
    """Record ``value`` of ``field`` in ``cell`` for ``column``; refuse one that differs
    from another column's (or another row's of this column)."""
    if value is None:
        return
    first = seen.setdefault((cell, field), (value, column))
    if first[0] != value:
        other = first[1] if first[1] != column else "itself"
        raise TrafficMismatch(
            f"{column} and {other} differ in {field} ({value} vs {first[0]}) in {cell}: "
            "only episodes of the same traffic are paired or pooled; evaluate them with "
            "the same settings"
        )

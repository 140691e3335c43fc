"""Evaluation grids: which (map, N, rho, style mix) cells an evaluation runs.

A :class:`Cell` is one traffic condition of paper Tables II-III. Grids:

* ``train``: the paper's training cells, ``train-25`` and ``train-50`` with
  N = 25, rho = 0.4, mix D1.
* ``zero-shot``: the paper's zero-shot rows (Tables III and IV), five per
  test map: N=25 rho=0.4 D2; N=25 rho=0.4 D3; N=20 rho=0.4 D1; N=30 rho=0.3
  D1; N=40 rho=0.2 D1, on ``test-25`` and on ``test-50``.
* ``zero-shot-product``: a wider grid of our own, the product of the values
  the paper's Experimental Setup lists, ``test-25`` / ``test-50`` x N in
  {20, 25, 30, 40} x rho in {0.2, 0.3} x mixes {D2, D3} (32 cells). It holds
  none of the paper's five rows (they keep rho = 0.4 or mix D1), which is why
  it is not the paper's grid.
* a TOML file, either listing cells explicitly::

      [[cells]]
      map = "test-50"
      n_vehicles = 40
      cav_penetration = 0.2
      style_mix = "D3"

  A cell with ``inflow_vph`` is a ``demand`` cell (:mod:`diacc.sim.scenario`):
  vehicles enter at that rate for the cell's ``demand_s`` seconds, the metrics
  skip its first ``warmup_s`` (both optional: the scenario defaults, 300 and
  0), and ``n_vehicles`` may be left out (it follows from the inflow). The
  cell, not the policy, fixes the traffic: a demand-trained checkpoint meets
  the same vehicles as the references (only its agent slots are its own).

  or as a product of value lists (every key optional, defaults as in ``train``;
  ``inflow_vph`` sweeps demand instead of N)::

      [product]
      map = ["test-25", "test-50"]
      n_vehicles = [20, 40]
      cav_penetration = [0.2]
      style_mix = ["D2"]

Unknown keys, maps or mixes raise :class:`GridError` with a one-line message.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.envs.observation import ObservationError, check_road
from diacc.errors import DiaccError
from diacc.fields import ConfigError
from diacc.sim.maps import MapError, load_map, map_tag
from diacc.sim.scenario import STYLE_MIXES, Demand, Scenario, draw_population
from diacc.tomlfile import read_toml

#: Named grids (see module docstring).
GRID_NAMES = ("train", "zero-shot", "zero-shot-product")
#: The paper's zero-shot rows (n_vehicles, cav_penetration, style_mix), in its
#: order; Tables III (25 % reduction) and IV (50 %) run each on the test map.
PAPER_ZERO_SHOT_ROWS = (
    (25, 0.4, "D2"),
    (25, 0.4, "D3"),
    (20, 0.4, "D1"),
    (30, 0.3, "D1"),
    (40, 0.2, "D1"),
)
#: Most cells of one grid file (a product of long lists must be an error, not a hang).
MAX_CELLS = 10_000
#: Columns that identify a cell in every results file, in this order.
CELL_KEYS = ("map", "n_vehicles", "cav_penetration", "style_mix")
#: Cell keys that may be left out: a demand cell's inflow (0: the paper's release).
OPTIONAL_CELL_KEYS = ("inflow_vph", "demand_s", "warmup_s")
#: First word of every evaluation seed's entropy; training seeds start with the
#: run seed (small integers), so evaluation episodes use other random streams.
EVAL_SEED_TAG = 0xE7A1_5EED
#: Evaluation seed streams. ``validation`` is for choosing (seeds, settings,
#: checkpoints), ``test`` for reporting: a number chosen on the episodes it is
#: reported on overstates itself (issue 42). The two are disjoint by
#: construction (validation seeds are even, test seeds odd). ``legacy`` is the
#: single stream every evaluation used before the two existed; results committed
#: before them were played on it and stay reproducible with ``--stream legacy``.
SEED_STREAMS = ("test", "validation", "legacy")
#: The stream ``diacc eval`` reports on unless told otherwise.
DEFAULT_STREAM = "test"
#: Second entropy word of each stream (legacy seeds have none: the old derivation).
_STREAM_WORDS = {"validation": 0x0A11_DA7E, "test": 0x07E5_7E57}
#: Lowest bit of each stream's seeds (what makes the two disjoint).
_STREAM_PARITY = {"validation": 0, "test": 1}


class GridError(DiaccError, ValueError):
    """A grid name or grid file is invalid; the message is one line."""


@dataclass(frozen=True, order=True)
class Cell:
    """One traffic condition: map x vehicle count x CAV share x HDV style mix."""

    map: str
    n_vehicles: int
    cav_penetration: float
    style_mix: str
    inflow_vph: float = 0.0  # > 0: a demand cell (vehicles enter at this rate)
    # A demand cell's timing (0: the scenario's defaults). Not part of the key: a
    # cell's seeds are the same at any timing (common random numbers).
    demand_s: float = 0.0
    warmup_s: float = 0.0

    @property
    def key(self) -> str:
        """Stable, file-name-safe identifier, e.g. ``train-25_N25_rho0.40_D1``
        (``train-50_Q3200_rho0.40_D1`` for a demand cell)."""
        size = f"Q{self.inflow_vph:.0f}" if self.inflow_vph else f"N{self.n_vehicles}"
        return f"{self.map}_{size}_rho{self.cav_penetration:.2f}_{self.style_mix}"

    @property
    def file_key(self) -> str:
        """:attr:`key` made safe as a file name inside ``--out``.

        A shipped map's cell keeps its key; a map file's path is replaced by
        its stem and content hash (:func:`~diacc.sim.maps.map_tag`): an absolute
        path once wrote the results next to the map file, a relative one
        crashed after the episodes ran. (:attr:`key` itself stays the cell's
        identity, from which its seeds are drawn.)
        """
        if Path(self.map).suffix != ".toml":
            return self.key
        return self.key.replace(self.map, map_tag(self.map), 1)

    def scenario(
        self, cav_penetration: float | None = None, base: Scenario | None = None
    ) -> Scenario:
        """The scenario of this cell (``cav_penetration`` overrides rho, e.g. 0 for pure HDV)."""
        base = base or Scenario()
        rho = self.cav_penetration if cav_penetration is None else cav_penetration
        size: dict = {"n_vehicles": self.n_vehicles}
        if self.inflow_vph:
            # The cell fixes the traffic, for every policy alike (a demand-trained
            # checkpoint's own timing would give it other vehicles than the references
            # it is compared with). N follows from it; the agent slots are the
            # policy's own until the evaluation sets them (EvalSettings.agent_slots,
            # every CAV by default).
            timing = Demand()
            size = {
                "kind": "demand",
                "inflow_vph": self.inflow_vph,
                "demand_s": self.demand_s or timing.demand_s,
                "warmup_s": self.warmup_s or timing.warmup_s,
                "cav_slots": (base if base.kind == "demand" else timing).cav_slots,
            }
        return Scenario(
            cav_penetration=rho,
            style_mix=self.style_mix,
            insert_start_m=base.insert_start_m,
            insert_spacing_m=base.insert_spacing_m,
            insert_speed_mps=base.insert_speed_mps,
            **size,
        )

    def seed(self, episode: int, stream: str) -> int:
        """Seed of episode ``episode`` of this cell in a seed stream (:data:`SEED_STREAMS`).

        Common seeds let policies be compared on identical traffic draws. The
        seed depends on the stream, the cell key and the episode only, and fits
        in 31 bits (SUMO's ``--seed`` is a signed 32-bit integer); its lowest
        bit is the stream's parity, so no validation seed is a test seed.
        """
        check_stream(stream)
        cell_word = zlib.crc32(self.key.encode())
        if stream == "legacy":
            words = [EVAL_SEED_TAG, cell_word, int(episode)]
            return int(np.random.SeedSequence(words).generate_state(1)[0] >> 1)
        words = [EVAL_SEED_TAG, _STREAM_WORDS[stream], cell_word, int(episode)]
        high = int(np.random.SeedSequence(words).generate_state(1)[0] >> 2)  # 30 bits
        return (high << 1) | _STREAM_PARITY[stream]

    def as_row(self) -> dict:
        return {
            "map": self.map,
            "n_vehicles": self.n_vehicles,
            "cav_penetration": self.cav_penetration,
            "style_mix": self.style_mix,
        }


def check_stream(stream: str) -> str:
    """``stream`` if it names a seed stream, else a one-line :class:`GridError`."""
    if stream not in SEED_STREAMS:
        raise GridError(f"unknown seed stream {stream!r}; use {', '.join(SEED_STREAMS)}")
    return stream


def _check_keys(values: dict, source: str) -> None:
    """Refuse a key no cell has, naming the first one: a single cell and a
    ``[product]`` table take the same keys, so a typo reads the same in both."""
    unknown = set(values) - set(CELL_KEYS) - set(OPTIONAL_CELL_KEYS)
    if unknown:
        raise GridError(
            f"{source}: unknown grid cell key {sorted(unknown)[0]!r}; "
            f"known keys: {', '.join(CELL_KEYS + OPTIONAL_CELL_KEYS)}"
        )


def make_cell(values: dict, source: str = "<grid>") -> Cell:
    """Validate one cell mapping (as read from TOML or CSV) into a :class:`Cell`."""
    if not isinstance(values, dict):
        raise GridError(f"{source}: a grid cell must be a table of {', '.join(CELL_KEYS)}")
    _check_keys(values, source)
    inflow = values.get("inflow_vph", 0.0)
    if not isinstance(inflow, (int, float)) or isinstance(inflow, bool) or inflow < 0:
        raise GridError(f"{source}: inflow_vph must be a positive number, got {inflow!r}")
    timing = {}
    for key in ("demand_s", "warmup_s"):
        value = values.get(key, 0.0)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not value >= 0:
            raise GridError(f"{source}: {key} must be a number >= 0, got {value!r}")
        if value and not inflow:
            raise GridError(f"{source}: {key} needs inflow_vph (a demand cell)")
        if key == "demand_s" and key in values and not value:  # 0 stands for the default
            raise GridError(
                f"{source}: demand_s must be > 0 s, got {value!r}; leave it out for the "
                f"default ({Demand().demand_s:g} s)"
            )
        timing[key] = float(value)
    if inflow and "n_vehicles" not in values:
        values = {**values, "n_vehicles": 1}  # set from the inflow below
    missing = [k for k in CELL_KEYS if k not in values]
    if missing:
        raise GridError(f"{source}: grid cell is missing key {missing[0]!r}")
    if not isinstance(values["map"], str):
        raise GridError(f"{source}: map must be a map name or .toml path, got {values['map']!r}")
    try:
        road = load_map(values["map"])
        check_road(road)  # the observation's road and lane tables hold it
    except (MapError, ObservationError) as exc:
        raise GridError(f"{source}: {exc}") from None
    n, rho, mix = values["n_vehicles"], values["cav_penetration"], values["style_mix"]
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise GridError(f"{source}: n_vehicles must be a positive integer, got {n!r}")
    if not isinstance(rho, (int, float)) or isinstance(rho, bool) or not 0 <= rho <= 1:
        raise GridError(f"{source}: cav_penetration must be a number in [0, 1], got {rho!r}")
    if not isinstance(mix, str) or mix not in STYLE_MIXES:
        raise GridError(f"{source}: unknown style mix {mix!r}; known: {', '.join(STYLE_MIXES)}")
    cell = Cell(str(values["map"]), int(n), float(rho), str(mix), float(inflow), **timing)
    try:
        scenario = cell.scenario()
        # Placing the vehicles checks that they fit the map (once found in the first
        # episode, after the results directory was written).
        draw_population(scenario, road, seed=0)
    except ConfigError as exc:
        raise GridError(f"{source}: {exc}") from None
    if inflow:  # N follows from the inflow and the cell's demand_s
        cell = dataclasses.replace(cell, n_vehicles=scenario.n_vehicles)
    return cell


def _product(values: dict, source: str) -> list[Cell]:
    defaults = {
        "map": ["train-25", "train-50"],
        "n_vehicles": [25],
        "cav_penetration": [0.4],
        "style_mix": ["D1"],
    }
    if not isinstance(values, dict):
        raise GridError(f"{source}: [product] must be a table of value lists")
    _check_keys(values, source)
    keys = CELL_KEYS + tuple(k for k in OPTIONAL_CELL_KEYS if k in values)
    lists = {k: values.get(k, defaults.get(k)) for k in keys}
    for key, value in lists.items():
        if not isinstance(value, list) or not value:
            raise GridError(f"{source}: product key {key!r} must be a non-empty list")
    size = math.prod(len(v) for v in lists.values())
    if size > MAX_CELLS:
        raise GridError(f"{source}: the product has {size} cells; at most {MAX_CELLS}")
    cells = [
        make_cell(dict(zip(keys, combo, strict=True)), source)
        for combo in itertools.product(*(lists[k] for k in keys))
    ]
    return sorted(set(cells), key=cells.index)  # demand cells of any N are one cell


def load_grid(name_or_path: str | Path) -> list[Cell]:
    """Cells of a named grid (:data:`GRID_NAMES`) or of a TOML grid file."""
    if str(name_or_path) == "train":
        return _product({}, "train")
    if str(name_or_path) == "zero-shot":
        return [
            make_cell(dict(zip(CELL_KEYS, (map_name, *row), strict=True)), "zero-shot")
            for map_name in ("test-25", "test-50")
            for row in PAPER_ZERO_SHOT_ROWS
        ]
    if str(name_or_path) == "zero-shot-product":
        return _product(
            {
                "map": ["test-25", "test-50"],
                "n_vehicles": [20, 25, 30, 40],
                "cav_penetration": [0.2, 0.3],
                "style_mix": ["D2", "D3"],
            },
            "zero-shot-product",
        )
    path = Path(name_or_path)
    if path.suffix != ".toml":
        raise GridError(
            f"unknown grid {str(name_or_path)!r}; use {', '.join(GRID_NAMES)} or a .toml grid file"
        )
    if not path.exists():
        raise GridError(f"grid file {path} does not exist")
    data = read_toml(path, GridError)
    unknown = set(data) - {"cells", "product"}
    if unknown:
        raise GridError(
            f"{path}: unknown top-level key {sorted(unknown)[0]!r}; "
            "use [[cells]] tables or one [product] table"
        )
    listed = data.get("cells", [])
    if not isinstance(listed, list) or len(listed) > MAX_CELLS:
        raise GridError(f"{path}: 'cells' must be a list of at most {MAX_CELLS} [[cells]] tables")
    cells = [make_cell(c, f"{path} cells[{i}]") for i, c in enumerate(listed)]
    if "product" in data:
        cells += _product(data["product"], f"{path} [product]")
    if not cells:
        raise GridError(f"{path}: grid file lists no cells")
    return sorted(set(cells), key=cells.index)

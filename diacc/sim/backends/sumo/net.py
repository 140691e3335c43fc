"""SUMO network files generated from a :class:`~diacc.sim.maps.Map`.

The map is the single description of the road; this module turns it into
plain SUMO node/edge/connection XML and runs the ``netconvert`` binary of the
eclipse-sumo wheel. Nothing hand-written in ``.net.xml`` form lives in the
repository, so the SUMO road cannot drift from the highway backend's road.

Layout: the route runs along SUMO's x axis from x = 0, one edge per segment
(``e0``, ``e1``...), with the right road edge at SUMO y = -max_lanes * lane
width, so absolute lane ``l`` is the straight line y = (l + 0.5) w - L w.
Each edge is given its nominal ``length`` and junction
internal links are disabled, so a lane position plus the edge's start is
exactly the route coordinate of the map. Lanes keep the map's absolute
numbering through explicit connections: SUMO lane ``k`` of segment ``s`` is
absolute lane ``Map.first_lane(s) + k``, and only lanes that exist on both
sides of a boundary are connected. A lane that ends therefore has no
successor, which makes LC2013 leave it with a *strategic* lane change before
its end (the behaviour of a real lane drop); lanes that open after a
reduction are reached by ordinary lane changes.

Networks are cached per ``Map.content_hash()`` in ``$DIACC_CACHE/sumo`` (or
``~/.cache/diacc/sumo``) and written atomically, so parallel workers can
share one file. File names are the hash alone: a map's ``name`` is a user
string (``"../../x"`` once wrote outside the cache). A cached network that
does not parse (a truncated file) is rebuilt; a cache folder that cannot be
created or written is replaced by one in the system's temporary folder, with
a warning.
"""

from __future__ import annotations

import os
import stat
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from xml.sax.saxutils import quoteattr

from diacc.fileio import atomic_write
from diacc.runlog import log
from diacc.sim.backends.base import BackendError
from diacc.sim.maps import Map

#: Route id used by every vehicle; it covers all edges of the map.
ROUTE_ID = "route"


def cache_dir() -> Path:
    """Folder for generated networks (``$DIACC_CACHE/sumo`` or ``~/.cache/diacc/sumo``)."""
    root = os.environ.get("DIACC_CACHE")
    base = Path(root) if root else Path.home() / ".cache" / "diacc"
    return base / "sumo"


def edge_id(segment_index: int) -> str:
    """SUMO edge id of a map segment."""
    return f"e{segment_index}"


def edge_ids(road: Map) -> list[str]:
    """Edge ids of the route, in driving order."""
    return [edge_id(s) for s in range(len(road.segments))]


def lane_ids(road: Map) -> dict[str, tuple[int, int]]:
    """``{SUMO lane id: (segment, absolute lane)}`` of every lane of the route.

    SUMO names lane ``k`` of edge ``e`` ``"e_k"``; it is absolute lane
    ``Map.first_lane(segment) + k`` (module docstring).
    """
    return {
        f"{edge_id(s)}_{k}": (s, road.first_lane(s) + k)
        for s, seg in enumerate(road.segments)
        for k in range(seg.lanes)
    }


def nodes_xml(road: Map) -> str:
    """Node file: one node per segment boundary on the x axis."""
    xs = [0.0, *road.segment_ends_m.tolist()]
    rows = [
        f'    <node id="n{i}" x="{x:.3f}" y="0.000" type="priority"/>' for i, x in enumerate(xs)
    ]
    return "<nodes>\n" + "\n".join(rows) + "\n</nodes>\n"


def edges_xml(road: Map) -> str:
    """Edge file: one edge per segment with its lane count, speed, width and length."""
    rows = []
    starts, ends = road.segment_starts_m, road.segment_ends_m
    for s, seg in enumerate(road.segments):
        # Lanes spread to the right of the edge line, which is therefore the
        # left border: put it where the map's left border of this segment is,
        # so that an absolute lane is one straight line over every edge.
        left_y = (road.first_lane(s) + seg.lanes - road.max_lanes) * road.lane_width_m
        rows.append(
            f'    <edge id="{edge_id(s)}" from="n{s}" to="n{s + 1}" priority="1" '
            f'numLanes="{seg.lanes}" speed="{seg.speed_limit_mps:.3f}" '
            f'width="{road.lane_width_m:.3f}" length="{seg.length_m:.3f}" '
            f'spreadType="right" shape="{starts[s]:.3f},{left_y:.3f} {ends[s]:.3f},{left_y:.3f}"/>'
        )
    return "<edges>\n" + "\n".join(rows) + "\n</edges>\n"


def connections_xml(road: Map) -> str:
    """Connection file: absolute lane ``l`` continues into absolute lane ``l`` only."""
    rows = []
    for s in range(len(road.segments) - 1):
        here, there = road.lane_range(s), road.lane_range(s + 1)
        for lane in here:
            if lane in there:
                rows.append(
                    f'    <connection from="{edge_id(s)}" to="{edge_id(s + 1)}" '
                    f'fromLane="{lane - here.start}" toLane="{lane - there.start}"/>'
                )
    return "<connections>\n" + "\n".join(rows) + "\n</connections>\n"


def routes_xml(road: Map) -> str:
    """Route file with the single route over every edge (vehicle types come from the worker)."""
    edges = " ".join(edge_ids(road))
    return f'<routes>\n    <route id={quoteattr(ROUTE_ID)} edges="{edges}"/>\n</routes>\n'


def build_network(road: Map, folder: Path | None = None) -> tuple[Path, Path]:
    """Return ``(net_path, route_path)`` for a map, running netconvert if not cached.

    Raises:
        BackendError: netconvert is missing or rejects the generated files.
    """
    folder = usable_cache(folder or cache_dir())
    stem = f"net-{road.content_hash()}"
    net_path = folder / f"{stem}.net.xml"
    route_path = folder / f"{stem}.rou.xml"
    routes = routes_xml(road)
    if not route_path.exists() or route_path.read_text(errors="replace") != routes:
        atomic_write(route_path, routes)
    if _complete_network(net_path, road):
        return net_path, route_path
    if net_path.exists():
        log.warning("cached SUMO network %s is damaged; rebuilding it", net_path)

    import sumolib  # local: only needed when a network must be built

    netconvert = sumolib.checkBinary("netconvert")
    with tempfile.TemporaryDirectory(prefix="diacc-net-") as tmp:
        tmp_dir = Path(tmp)
        (tmp_dir / "map.nod.xml").write_text(nodes_xml(road))
        (tmp_dir / "map.edg.xml").write_text(edges_xml(road))
        (tmp_dir / "map.con.xml").write_text(connections_xml(road))
        out = tmp_dir / "map.net.xml"
        cmd = [
            netconvert,
            "--node-files", str(tmp_dir / "map.nod.xml"),
            "--edge-files", str(tmp_dir / "map.edg.xml"),
            "--connection-files", str(tmp_dir / "map.con.xml"),
            "--output-file", str(out),
            "--no-internal-links", "true",
            "--no-turnarounds", "true",
            "--offset.disable-normalization", "true",
            "--junctions.corner-detail", "0",
            "--default.spreadtype", "right",
            "--no-warnings", "true",
        ]  # fmt: skip
        try:
            result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise BackendError(f"netconvert failed for map {road.name!r}: {exc}") from None
        if result.returncode != 0 or not out.exists():
            last = (result.stderr.strip().splitlines() or ["no output"])[-1]
            raise BackendError(f"netconvert failed for map {road.name!r}: {last}")
        atomic_write(net_path, out.read_text())
    return net_path, route_path


def _complete_network(path: Path, road: Map) -> bool:
    """Whether ``path`` is a parseable network holding every edge of ``road``."""
    if not path.exists():
        return False
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return False
    found = {edge.get("id") for edge in root.iter("edge")}
    return root.tag == "net" and set(edge_ids(road)) <= found


def usable_cache(folder: Path) -> Path:
    """``folder`` if networks can be written there, else a per-user temporary folder (warned)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if os.access(folder, os.W_OK | os.X_OK):
            return folder
        reason = "not writable"
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
    fallback = Path(tempfile.gettempdir()) / f"diacc-{os.getuid()}" / "sumo"
    log.warning("SUMO network cache %s is unusable (%s); using %s", folder, reason, fallback)
    try:
        for part in (fallback.parent, fallback):
            part.mkdir(mode=0o700, exist_ok=True)
            _check_private(part)
    except OSError as exc:
        raise BackendError(
            f"no usable SUMO network cache: {folder} ({reason}), {fallback} ({exc.strerror}); "
            "set DIACC_CACHE to a writable folder"
        ) from None
    return fallback


def _check_private(folder: Path) -> None:
    """Refuse a folder in a shared place that another user could have planted files in.

    Anyone can create ``$TMPDIR/diacc-<uid>`` first and put a network there that
    the SUMO worker would load; so the folder must be ours, not a link, and not
    writable by group or others.
    """
    info = os.lstat(folder)
    if not stat.S_ISDIR(info.st_mode):
        problem = "is not a folder (a link?)"
    elif info.st_uid != os.getuid():
        problem = f"belongs to user {info.st_uid}"
    elif info.st_mode & 0o022:
        problem = "is writable by other users"
    else:
        return
    raise BackendError(
        f"SUMO network cache {folder} {problem}; refused (another user could plant "
        "networks there): remove it or set DIACC_CACHE to a folder of yours"
    )

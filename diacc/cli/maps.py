"""``diacc maps generate``: a generated bottleneck map as a TOML file (registered by
:mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from diacc.cli.options import add_command
from diacc.sim.mapgen import MAP_STREAMS, NAME_PREFIX, STREAM_SEEDS


def add_parsers(sub) -> None:
    p = add_command(
        sub,
        "maps",
        "generated bottleneck maps (diacc.sim.mapgen)",
        f"A generated map is named {NAME_PREFIX}<stream>-<index> (e.g. {NAME_PREFIX}test-7);\n"
        "every --map option takes that name. 'generate' prints its TOML, an ordinary\n"
        "map file to keep, edit or pass as --map FILE.toml.",
    )
    maps_sub = p.add_subparsers(dest="maps_action", required=True, metavar="ACTION")
    q = maps_sub.add_parser(
        "generate",
        help="print (or write) one generated map as TOML",
        description="One generated map as TOML: map --index of a --stream (train,\n"
        f"validation, test: disjoint seed ranges of {STREAM_SEEDS:,} maps each), or\n"
        "the map of a generator --seed (stream k owns the seeds from k * "
        f"{STREAM_SEEDS:,}).",
    )
    which = q.add_mutually_exclusive_group(required=True)
    which.add_argument("--seed", type=int, help="generator seed (it names its stream and index)")
    which.add_argument("--index", type=int, help="map index within --stream")
    q.add_argument("--stream", choices=MAP_STREAMS, default=None, help="stream of --index")
    q.add_argument("--out", type=Path, default=None, help="write this file (default: stdout)")


def cmd_maps(args: argparse.Namespace) -> None:
    from diacc.fileio import atomic_write
    from diacc.sim.mapgen import generator_seed, map_toml
    from diacc.sim.maps import MapError

    if args.seed is not None and args.stream is not None:
        raise MapError("give --seed or --stream with --index, not both (a seed names its stream)")
    if args.index is not None and args.stream is None:
        raise MapError(f"--index needs --stream ({', '.join(MAP_STREAMS)})")
    seed = args.seed if args.seed is not None else generator_seed(args.stream, args.index)
    text = map_toml(seed)
    if args.out is None:
        print(text, end="")
    else:
        atomic_write(args.out, text)
        print(f"wrote {args.out}")


COMMANDS = {"maps": cmd_maps}

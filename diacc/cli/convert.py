"""``diacc convert-checkpoint``: old checkpoints in today's format (registered by
:mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from diacc.cli.options import add_command


def add_parsers(sub) -> None:
    p = add_command(
        sub,
        "convert-checkpoint",
        "rewrite old (format 1) checkpoints in today's format",
        "Format 1 kept numpy's RNG state as a pickled array, which a safe load\n"
        "(torch weights_only) refuses. Converting reads numpy arrays besides tensors\n"
        "and plain values, nothing else; the networks are copied bit for bit.",
    )
    p.add_argument("paths", nargs="+", type=Path, metavar="FILE", help="checkpoints to convert")
    p.add_argument(
        "--suffix",
        default="",
        help="write FILE with this suffix added to the stem (e.g. -v2) instead of in place",
    )


def cmd_convert(args: argparse.Namespace) -> None:
    from diacc.learn.checkpoint import convert_checkpoint

    for path in args.paths:
        dst = path.with_name(f"{path.stem}{args.suffix}{path.suffix}")
        print(f"converted {path} -> {convert_checkpoint(path, dst)}")


COMMANDS = {"convert-checkpoint": cmd_convert}

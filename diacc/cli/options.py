"""Option pieces every ``diacc`` command shares: how a subcommand is added, the common
options (``--out`` with its former names, ``--device``, the scale-out engine's), and
argparse types (seeds, comma-separated lists), so that one option reads the same on every
command. Ray is imported only when ``--engine ray`` is chosen
(:mod:`diacc.experiments.scaleout`).
"""

from __future__ import annotations

import argparse
import dataclasses

from diacc.config import ConfigError, TrainConfig

#: ``--device`` choices: those of :attr:`TrainConfig.device <diacc.config.TrainConfig>`.
DEVICES = next(f for f in dataclasses.fields(TrainConfig) if f.name == "device").metadata["choices"]


def add_command(sub, name: str, summary: str, description: str = "") -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` starts with its summary (and description):
    the list of commands and each command's own help then say the same."""
    text = summary[0].upper() + summary[1:] + "." + (f"\n\n{description}" if description else "")
    return sub.add_parser(name, help=summary, description=text)


def add_renamed_arg(p: argparse.ArgumentParser, name: str, old_name: str, **kwargs) -> None:
    """Option ``name`` and ``old_name`` (its former spelling) as a hidden alias of the
    same ``dest``, so that old command lines still run while ``--help`` shows one name
    per meaning. Give ``dest``: argparse would derive the alias's own from its name."""
    p.add_argument(name, **kwargs)
    alias = {k: v for k, v in kwargs.items() if k != "default"}
    p.add_argument(old_name, **{**alias, "help": argparse.SUPPRESS, "default": argparse.SUPPRESS})


def add_out_arg(p: argparse.ArgumentParser, old_name: str, **kwargs) -> None:
    """``--out``, every command's name for where it writes, with ``old_name`` (the
    command's former name for it) as a hidden alias (:func:`add_renamed_arg`)."""
    add_renamed_arg(p, "--out", old_name, **kwargs)


def add_device_arg(
    p: argparse.ArgumentParser, what: str = "torch device of the PPO update"
) -> None:
    """``--device``, the same choices and default on every command: None, which stands
    for :attr:`TrainConfig.device <diacc.config.TrainConfig>` (``auto``) unless a
    ``--config`` file names another, so that ``train``, ``sweep``, ``reproduce`` and
    ``bench`` pick the same device for the same command line."""
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=None,
        help=f"{what}; auto: cuda if this machine has it, else cpu (TrainConfig's default, "
        f"so that every command picks the same device) (default: {TrainConfig.device})",
    )


def add_engine_args(p: argparse.ArgumentParser) -> None:
    """``--engine``, ``--ray-address``, ``--ray-cpus``."""
    p.add_argument(
        "--engine",
        choices=("local", "ray"),
        default="local",
        help="local: processes on this machine; ray: Ray tasks (pip install -e '.[ray]')",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="Ray cluster to join (auto, HOST:6379 or ray://HOST:10001); "
        "default: start a local Ray instance",
    )
    p.add_argument(
        "--ray-cpus",
        type=int,
        default=None,
        help="CPUs of the local Ray instance (default: all of this machine's)",
    )


def eval_engine(args: argparse.Namespace):
    """The evaluation engine the options ask for (None: the local worker pool)."""
    if args.engine == "local":
        if args.ray_address or args.ray_cpus:
            raise ConfigError("--ray-address / --ray-cpus need --engine ray")
        return None
    from diacc.experiments.scaleout import RayEngine

    return RayEngine(args.ray_address, args.ray_cpus)


def seed_type(text: str) -> int:
    """An argparse type: a traffic seed, a whole number in [0, 2^32 - 1] (numpy's range)."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 0 <= seed < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^32 - 1], got {seed}")
    return seed


def csv_list(text: str, kind=str) -> list:
    """The entries of a comma-separated option value (``--seeds 1,2,3``), each ``kind``."""
    try:
        values = [kind(v.strip()) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(
            f"expected a comma-separated list of {kind.__name__}, got {text!r}"
        ) from None
    if not values:
        raise ConfigError(f"expected a comma-separated list, got {text!r}")
    return values


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1 (argparse prints the one-line error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def slots_type(*names: str):
    """argparse type of ``--agent-slots``: one of ``names`` or a cap N >= 1 (the CAVs a
    policy drives at once); the config that takes it checks the cap's upper bound."""

    def parse(text: str) -> int | str:
        if text in names:
            return text
        try:
            return positive_int(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(
                f"must be {' or '.join(names)} or a whole number >= 1, got {text!r}"
            ) from None

    parse.__name__ = "agent slots"  # argparse names the type in its error
    return parse

"""The ``diacc`` parser: its help format and one subparser per command.

Each command module (:mod:`.train`, :mod:`.bench`, :mod:`.simulate`, :mod:`.convert`,
:mod:`.eval`, :mod:`.scale`, :mod:`.reproduce`, :mod:`.maps`) adds its subcommands
(``add_parsers``) and names their handlers (``COMMANDS``); :data:`COMMAND_MODULES` is
their order in ``diacc --help``. Handlers import the modules they run when called, so
that ``--help`` stays quick.
"""

from __future__ import annotations

import argparse

from diacc import __version__
from diacc.cli import bench, convert, maps, reproduce, scale, simulate, train
from diacc.cli import eval as evaluate

DESCRIPTION = """\
diacc: multi-agent reinforcement learning for connected automated vehicles
(CAVs) among human drivers in highway bottlenecks, on highway-env and SUMO.
Run 'diacc COMMAND --help' for a command's options; every option shows its
default."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows each option's default, except where there is none to show (None, off
    flags: their help says what happens then); keeps descriptions' line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or action.default == []:
            return action.help or ""
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """``diacc``'s parser: its help formatter on every (sub)command."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        """A bad option is one line, like every other error (argparse printed the usage first,
        several lines for the larger commands)."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


#: Command modules, in the order ``diacc --help`` lists their commands.
COMMAND_MODULES = (train, bench, simulate, convert, evaluate, scale, reproduce, maps)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="diacc", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"diacc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMAND_MODULES:
        module.add_parsers(sub)
    return parser

"""Command line: ``diacc train | eval | sweep | reproduce | table | plot | render | scorecard |
simulate | bench | convert-checkpoint | maps``.

This module runs a command (:func:`main`, also ``python -m diacc.cli``): it parses the
command line (:mod:`.parser`, one module per command: :mod:`.train`, :mod:`.bench`,
:mod:`.simulate`, :mod:`.convert`; :mod:`.eval` has ``eval``, ``table``, ``plot``,
``render``, ``scorecard``; :mod:`.scale` ``sweep``; :mod:`.reproduce` ``reproduce``;
:mod:`.maps` ``maps generate``; :mod:`.options` the options they share), calls the
command's handler and turns its failures into exit codes. The command line sits above
every other layer and nothing in ``diacc`` imports it.

Every command turns known failures (bad map, backend, config key, checkpoint,
crashed simulator: a :class:`~diacc.errors.DiaccError`) into a one-line
``diacc: error: ...`` message and exit code 2 (set ``DIACC_DEBUG=1`` to see
the traceback); any other exception is a bug and shows its traceback.
Recoveries are one ``diacc: warning: ...`` line each (:mod:`diacc.runlog`);
an interrupted ``train`` exits with 128 + the signal number after saving a
checkpoint; a closed output pipe (``diacc simulate | head``) ends quietly.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from diacc.cli.parser import COMMAND_MODULES, build_parser
from diacc.errors import DiaccError

__all__ = ["COMMANDS", "build_parser", "main"]

#: Command name -> handler, of every command module.
COMMANDS = {name: cmd for module in COMMAND_MODULES for name, cmd in module.COMMANDS.items()}


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread like SIGINT's KeyboardInterrupt."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = signum

    def __str__(self) -> str:
        return f"terminated ({signal.Signals(self.signum).name})"


#: Signals that end a command the way SIGINT does (a closed terminal sends SIGHUP).
TERMINATING = (signal.SIGTERM, signal.SIGHUP)
#: Set by the handler: libraries that catch the exception and raise a bare
#: KeyboardInterrupt of their own (Ray's ``wait``/``get``) lose its type.
_signal_seen: int | None = None


def _terminated(signum: int, frame) -> None:
    global _signal_seen
    _signal_seen = signum
    raise Terminated(signum)


def main(argv: list[str] | None = None) -> int:
    from diacc.runlog import enable_stderr

    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # recorded by `reproduce`
    enable_stderr()
    main_thread = threading.current_thread() is threading.main_thread()
    global _signal_seen
    _signal_seen = None
    # SIGTERM and SIGHUP as SIGINT: an exception, so that every `finally` ends its
    # children (pool and vector-env workers, SUMO, a local Ray) instead of orphaning them.
    previous = {s: signal.signal(s, _terminated) for s in TERMINATING} if main_thread else {}
    try:
        return _run(args)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _run(args: argparse.Namespace) -> int:
    try:
        COMMANDS[args.command](args)
        sys.stdout.flush()  # here, so that a closed pipe is caught below
    except DiaccError as exc:
        if os.environ.get("DIACC_DEBUG"):
            raise
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        # A fault of the user's own code (their controller) shows their frames first.
        sys.stderr.write(getattr(exc, "user_traceback", ""))
        print(f"diacc: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # TrainingInterrupted says which signal and what was saved
        if _signal_seen and not hasattr(exc, "signum"):
            exc = Terminated(_signal_seen)
        print(f"diacc: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 128 + getattr(exc, "signum", 2)
    except BrokenPipeError:
        # The reader (``diacc simulate | head``) has gone: stop quietly, as Unix tools do.
        # stdout is pointed at /dev/null so that the interpreter's final flush cannot fail.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    return 0

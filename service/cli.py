"""The ``loopwatch`` command line.

Every subcommand is a module of :mod:`service.commands` with
``register(commands)``; :data:`COMMANDS` lists them all, in the order
``loopwatch --help`` shows them.  To add a command, write its module and name
it in :data:`COMMANDS`.  ``loopwatch COMMAND --help`` tells what each does.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from service.commands import (
    CliError,
    analyze,
    compensate,
    demo,
    model_check,
    plant_sim,
    predict,
    report,
    serve,
    simulate,
    unit_analyze,
)

COMMANDS = (
    simulate, analyze, serve, demo, predict, compensate, plant_sim, unit_analyze, model_check,
    report,
)
"""The command modules of ``loopwatch``, in the order of ``--help``."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``loopwatch``."""
    parser = argparse.ArgumentParser(prog="loopwatch", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.register(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``loopwatch`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.handler(args))
    except CliError as exc:
        print(f"loopwatch {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

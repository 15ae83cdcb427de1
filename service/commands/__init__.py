"""The subcommands of ``loopwatch``, a module each.

Every command is a module of this package with ``register(commands)``, which
adds its subparser to the ``add_subparsers()`` object (:data:`Subcommands`)
and sets ``handler`` (a function taking the parsed arguments and returning
the exit status).  :data:`service.cli.COMMANDS` lists the modules, in the
order ``loopwatch --help`` shows them: adding a command is writing its module
and naming it there.  A user error is raised as :class:`CliError`: printed
without a traceback, exit 2.

This package imports no command module itself, so a command such as
``plant-sim`` loads nothing else of the service.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

if TYPE_CHECKING:
    from service.loop_csv import LoopData

    Subcommands: TypeAlias = argparse._SubParsersAction[argparse.ArgumentParser]
else:  # the class is generic only to the type checker
    Subcommands = argparse._SubParsersAction
"""What ``register`` of a command module is given: ``add_subparsers()`` of ``loopwatch``."""

__all__ = ["CliError", "Subcommands", "read_json_file", "read_loop_file"]


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def read_json_file(path: Path) -> Any:
    """The JSON of ``path``; a missing file or invalid JSON as :class:`CliError`."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise CliError(f"{path}: no such file") from None
    except json.JSONDecodeError as exc:
        raise CliError(
            f"{path}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None


def read_loop_file(args: argparse.Namespace, *, min_samples: int = 2, context: str = "",
                   **columns: str) -> LoopData:
    """The loop data of ``args.file`` with the options ``--ts`` and ``--time``, ``--op``...
    (``columns`` overrides them); its warnings printed to stderr.

    Raises
    ------
    CliError
        The file cannot be read as loop data (the message, after ``context``).
    """
    # imported here: a command such as plant-sim loads nothing else of the service
    from service.loop_csv import LoopCsvError, read_loop_csv

    names = {name: getattr(args, name, None) for name in ("time", "op", "pv", "sp", "mv")}
    try:
        data = read_loop_csv(args.file, ts=args.ts, min_samples=min_samples,
                             **(names | columns))
    except LoopCsvError as exc:
        raise CliError(f"{context}{exc}") from None
    for warning in data.warnings:
        print(f"{args.file}: warning: {context}{warning}", file=sys.stderr)
    return data

"""Subcommands of ``loopwatch`` that live in their own modules.

Each module in :data:`COMMAND_MODULES` has ``register(commands)``, which adds
its subparser to the ``add_subparsers()`` object and sets ``handler`` (a
function taking the parsed arguments and returning the exit status).  A user
error is raised as :class:`CliError`: printed without a traceback, exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.loop_csv import LoopData

__all__ = ["COMMAND_MODULES", "CliError", "command_modules", "read_json_file", "read_loop_file"]


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


COMMAND_MODULES: tuple[str, ...] = (
    "predict", "compensate", "plant_sim", "unit_analyze", "model_check", "report"
)
"""Modules (under ``service.commands``) whose ``register`` adds a subcommand."""


def command_modules() -> list[ModuleType]:
    """The imported command modules, in :data:`COMMAND_MODULES` order."""
    return [importlib.import_module(f"service.commands.{name}") for name in COMMAND_MODULES]


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

"""Subcommands of ``loopwatch`` that live in their own modules.

Each module in :data:`COMMAND_MODULES` has ``register(commands)``, which adds
its subparser to the ``add_subparsers()`` object and sets ``handler`` (a
function taking the parsed arguments and returning the exit status).  A user
error is raised as :class:`CliError`: printed without a traceback, exit 2.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from types import ModuleType
from typing import Any

__all__ = ["COMMAND_MODULES", "CliError", "command_modules", "read_json_file"]


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

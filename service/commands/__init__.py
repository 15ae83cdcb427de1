"""Subcommands of ``loopwatch`` that live in their own modules.

Each module in :data:`COMMAND_MODULES` has ``register(commands)``, which adds
its subparser to the ``add_subparsers()`` object and sets ``handler`` (a
function taking the parsed arguments and returning the exit status).  A user
error is raised as :class:`CliError`: printed without a traceback, exit 2.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["COMMAND_MODULES", "CliError", "command_modules"]


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


COMMAND_MODULES: tuple[str, ...] = ("predict", "compensate", "plant_sim", "unit_analyze")
"""Modules (under ``service.commands``) whose ``register`` adds a subcommand."""


def command_modules() -> list[ModuleType]:
    """The imported command modules, in :data:`COMMAND_MODULES` order."""
    return [importlib.import_module(f"service.commands.{name}") for name in COMMAND_MODULES]

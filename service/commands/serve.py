"""``loopwatch serve``: the monitoring service.

::

    loopwatch serve [--config PLANT.yaml] [--host H] [--port P]
                    [--role api|ingest|scheduler|all]

Runs the service (:func:`service.server.serve`): REST API, analyses, alarms
and tickets.  Without a plant file it runs the simulated demo plant.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.commands import CliError, Subcommands

__all__ = ["register"]


def register(commands: Subcommands) -> None:
    """Add ``serve`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser("serve", help="run the monitoring service (REST API)")
    parser.add_argument("--config", type=Path, help="plant YAML file (default: the demo plant)")
    parser.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to listen on (default 8000)")
    parser.add_argument(
        "--role", choices=("api", "ingest", "scheduler", "all"),
        help="what this process runs (default all; see LOOPWATCH_ROLE): the API, the "
             "connectors of its ingest shard, the analysis scheduler (one leads, others "
             "stand by), or all of them",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``loopwatch serve`` until interrupted."""
    # imported here: the other commands need none of the server's stack
    from pydantic import ValidationError

    from service.config import ConfigError
    from service.executors import ExecutorError
    from service.server import serve

    try:
        serve(args.config, host=args.host, port=args.port, role=args.role)
    except KeyboardInterrupt:  # Ctrl+C: uvicorn has shut down cleanly, then re-raised it
        print("loopwatch: stopped", file=sys.stderr)
    except (ConfigError, ExecutorError) as exc:
        raise CliError(str(exc)) from None
    except ValidationError as exc:
        raise CliError(f"invalid LOOPWATCH_* settings: {exc}") from None
    return 0

"""``loopwatch plant-sim``: serve the simulated plant over OPC UA and Modbus TCP.

::

    loopwatch plant-sim [--host H] [--opcua-port P] [--modbus-port Q] [--speed X]
                        [--horizon S] [--print-map] [--config-out plant.yaml]
                        [--duration S]

Runs :class:`connectors.plant_sim.PlantSimulator` until interrupted (or for
``--duration`` seconds; ``--duration 0`` only prints the map and writes the
configuration).  ``--config-out`` writes the plant file that ``loopwatch
serve --config`` reads to watch this plant.  The command imports nothing
else of the service, so it runs as a plant of its own.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
from pathlib import Path

import yaml

from connectors.plant_sim import PlantSimulator
from service.commands import CliError, Subcommands

__all__ = ["register", "run_plant_sim"]


def register(commands: Subcommands) -> None:
    """Add ``plant-sim`` to the subcommands of ``loopwatch``."""
    parser = commands.add_parser(
        "plant-sim", help="serve simulated loops over OPC UA and Modbus TCP"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (127.0.0.1)")
    parser.add_argument("--opcua-port", type=int, default=4840, help="OPC UA port (4840)")
    parser.add_argument("--modbus-port", type=int, default=5020,
                        help="Modbus TCP port (5020); 0 serves OPC UA only")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="plant seconds per wall-clock second (1)")
    parser.add_argument("--horizon", type=float, default=12 * 3600.0,
                        help="plant seconds simulated ahead before the runs repeat (43200)")
    parser.add_argument("--print-map", action="store_true",
                        help="print the address map (tag, OPC UA node id, Modbus register)")
    parser.add_argument("--config-out", type=Path,
                        help="write the plant configuration for `loopwatch serve --config`")
    parser.add_argument("--duration", type=float,
                        help="stop after this many seconds (0: print and write, then exit)")
    parser.set_defaults(handler=run_plant_sim)


def _port(value: int, option: str, *, allow_zero: bool = False) -> int:
    if not (1 <= value <= 65535 or (allow_zero and value == 0)):
        raise CliError(f"{option} must be a TCP port 1-65535, got {value}")
    return value


def run_plant_sim(args: argparse.Namespace) -> int:
    """Handler of ``loopwatch plant-sim``."""
    _port(args.opcua_port, "--opcua-port")
    _port(args.modbus_port, "--modbus-port", allow_zero=True)
    for option, value in (("--speed", args.speed), ("--horizon", args.horizon)):
        if not (math.isfinite(value) and value > 0):
            raise CliError(f"{option} must be a positive number, got {value}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration >= 0):
        raise CliError(f"--duration must be 0 or more seconds, got {args.duration}")
    plant = PlantSimulator(
        host=args.host, opcua_port=args.opcua_port, modbus_port=args.modbus_port or None,
        speed=args.speed, horizon_s=args.horizon,
    )
    if args.print_map:
        print(plant.format_address_map())
    if args.config_out is not None:
        try:
            args.config_out.write_text(yaml.safe_dump(plant.plant_config(), sort_keys=False))
        except OSError as exc:
            raise CliError(f"{args.config_out}: cannot write: {exc.strerror}") from None
        print(f"wrote the plant configuration to {args.config_out}", file=sys.stderr)
    if args.duration == 0:
        return 0
    print(f"serving {len(plant.tags)} tags on {plant.opcua_url}"
          + (f" and modbus port {args.modbus_port}" if args.modbus_port else "")
          + f" at {args.speed:g} x real time (Ctrl-C stops)", file=sys.stderr)
    try:
        asyncio.run(plant.run(args.duration))
    except OSError as exc:
        raise CliError(f"cannot serve: {exc}") from None
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    return 0

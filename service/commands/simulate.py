"""``loopwatch simulate NAME|MODEL.json [--out FILE] [--duration S] [--list]``.

Simulates a named scenario (``--list`` shows them, :mod:`analytics.scenarios`)
or a JSON model file (format: :class:`analytics.simulation.ClosedLoopModel`)
and writes the time series as CSV.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path
from typing import TextIO

from analytics.errors import AnalyticsError
from analytics.scenarios import SCENARIOS, build_scenario
from analytics.simulation import ClosedLoopModel, SimulationResult
from service.commands import CliError, Subcommands, read_json_file

__all__ = ["register", "write_csv"]


def register(commands: Subcommands) -> None:
    """Add ``simulate`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser("simulate", help="simulate a scenario or a JSON model, write CSV")
    parser.add_argument("model", nargs="?", help="scenario name or MODEL.json")
    parser.add_argument("--out", help="CSV file to write (default: standard output)")
    parser.add_argument("--duration", type=float, help="simulated time in seconds")
    parser.add_argument("--list", action="store_true", help="list the named scenarios")
    parser.set_defaults(handler=run)


def _load_model(source: str) -> ClosedLoopModel:
    if source in SCENARIOS:
        return build_scenario(source)
    path = Path(source)
    if not path.suffix == ".json":
        raise CliError(
            f"{source!r} is neither a scenario name ({', '.join(SCENARIOS)}) nor a .json model file"
        )
    spec = read_json_file(path)
    try:
        return ClosedLoopModel.from_dict(spec)
    except AnalyticsError as exc:
        raise CliError(f"{path}: {exc}") from None


def write_csv(result: SimulationResult, out: TextIO) -> None:
    """Write a simulation as CSV, one row per sample, 6 significant digits."""
    columns = result.columns()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    for row in zip(*columns.values(), strict=True):
        writer.writerow([f"{value:.6g}" for value in row])


def run(args: argparse.Namespace) -> int:
    """Run ``loopwatch simulate``."""
    if args.list:
        for name, scenario in SCENARIOS.items():
            print(f"{name:22s} {scenario.description}")
        return 0
    if not args.model:
        raise CliError("simulate needs a scenario name or a model file (see --list)")
    model = _load_model(args.model)
    try:
        result = model.run(duration=args.duration)
    except AnalyticsError as exc:
        raise CliError(str(exc)) from None
    if args.out:
        with open(args.out, "w", newline="") as handle:
            write_csv(result, handle)
        print(
            f"wrote {result.t.size} samples of {len(result.names)} loop(s) to {args.out}",
            file=sys.stderr,
        )
    else:
        write_csv(result, sys.stdout)
    return 0

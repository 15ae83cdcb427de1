"""The ``loopwatch`` command line.

Commands that exist so far:

``loopwatch simulate NAME|MODEL.json [--out FILE] [--duration S]``
    Simulate a named scenario (``--list`` shows them) or a JSON model file
    (format: :class:`analytics.simulation.ClosedLoopModel`) and write the
    time series as CSV.
``loopwatch demo``
    Simulate the thesis scenarios and print what a control engineer would
    check first: does each loop oscillate, at what period, how big.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from analytics.errors import AnalyticsError
from analytics.oscillation import detect_oscillations
from analytics.scenarios import SCENARIOS, build_scenario
from analytics.simulation import ClosedLoopModel, SimulationResult


class CliError(Exception):
    """A user error: printed without a traceback, exit status 2."""


def _load_model(source: str) -> ClosedLoopModel:
    if source in SCENARIOS:
        return build_scenario(source)
    path = Path(source)
    if not path.suffix == ".json":
        raise CliError(
            f"{source!r} is neither a scenario name ({', '.join(SCENARIOS)}) nor a .json model file"
        )
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise CliError(f"{path}: no such file") from None
    except json.JSONDecodeError as exc:
        raise CliError(
            f"{path}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
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


def _cmd_simulate(args: argparse.Namespace) -> int:
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


def _cmd_demo(args: argparse.Namespace) -> int:
    print("loopwatch demo: simulated loops and what the oscillation detector sees in PV")
    print("(second half of each run; alarms and tickets come with the service)\n")
    header = ("scenario", "loop", "oscillating", "period s", "PV ampl.", "valve moves")
    print("{:22s} {:6s} {:>11s} {:>9s} {:>9s} {:>11s}".format(*header))
    for name, scenario in SCENARIOS.items():
        result = scenario.build().run()
        late = result.t >= result.t[-1] / 2
        for i, loop in enumerate(result.names):
            report = detect_oscillations(result.pv[i][late], result.dt)
            main = report.oscillations[0] if report.detected else None
            moves = int(np.count_nonzero(np.diff(result.mv[i][late])))
            period = f"{main.period_s:9.1f}" if main else f"{'-':>9s}"
            amplitude = f"{main.amplitude:9.3f}" if main else f"{'-':>9s}"
            verdict = "yes" if main else "no"
            print(f"{name:22s} {loop:6s} {verdict:>11s} {period} {amplitude} {moves:11d}")
    print("\nWrite any of these as CSV with: loopwatch simulate NAME --out FILE.csv")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``loopwatch``."""
    parser = argparse.ArgumentParser(prog="loopwatch", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    sim = commands.add_parser("simulate", help="simulate a scenario or a JSON model, write CSV")
    sim.add_argument("model", nargs="?", help="scenario name or MODEL.json")
    sim.add_argument("--out", help="CSV file to write (default: standard output)")
    sim.add_argument("--duration", type=float, help="simulated time in seconds")
    sim.add_argument("--list", action="store_true", help="list the named scenarios")
    sim.set_defaults(handler=_cmd_simulate)
    demo = commands.add_parser("demo", help="simulate the thesis scenarios and summarise them")
    demo.set_defaults(handler=_cmd_demo)
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

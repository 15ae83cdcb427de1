"""``loopwatch demo``: the thesis scenarios simulated, and what a control engineer
would check first: does each loop oscillate, at what period, how big."""

from __future__ import annotations

import argparse

import numpy as np

from analytics.oscillation import detect_oscillations
from analytics.scenarios import SCENARIOS
from service.commands import Subcommands

__all__ = ["register"]


def register(commands: Subcommands) -> None:
    """Add ``demo`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser("demo", help="simulate the thesis scenarios and summarise them")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``loopwatch demo``."""
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

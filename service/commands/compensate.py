"""``loopwatch compensate [--json]``: stiction compensators compared on the chapter 4 loop.

The thesis chapter 4 example (G = 0.66 e^-2.6s/(6.7s+1), Gc = 0.1 + 0.09/s,
He valve fs = 3, fd = 2, SP = 2 above the operating point): no compensation,
Hagglund's knocker, constant reinforcement and the model-based compensator,
judged by PV error (IAE), valve travel and stem reversals
(:func:`analytics.compensation.compare_compensators`); then the sensitivity of
the model-based compensator to errors in fs, fd and K beside thesis Tables
4.2-4.4 (:func:`analytics.compensation.model_based_sensitivity`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Sequence
from typing import Any, TextIO

from analytics.compensation import (
    CompensationMetrics,
    SensitivityRow,
    compare_compensators,
    model_based_sensitivity,
)
from analytics.errors import AnalyticsError
from service.commands import CliError, Subcommands


def register(commands: Subcommands) -> None:
    """Add ``compensate`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser(
        "compensate",
        help="compare stiction compensators on the thesis chapter 4 loop",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    parser.add_argument(
        "--compensate-from",
        type=float,
        default=1000.0,
        help="time the compensators are switched on, s (default 1000)",
    )
    parser.add_argument(
        "--duration", type=float, default=4000.0, help="simulated time, s (default 4000)"
    )
    parser.add_argument(
        "--switch-on",
        type=float,
        nargs="+",
        default=[1000.0, 1100.0, 1200.0, 1300.0],
        metavar="T",
        help="switch-on times of the sensitivity runs, s (default 1000 1100 1200 1300)",
    )
    parser.add_argument("--no-sensitivity", action="store_true", help="skip the sensitivity study")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=run)


def _row(item: Any) -> dict[str, Any]:
    """A result row for JSON, NaN as null."""
    return {
        key: None if isinstance(value, float) and math.isnan(value) else value
        for key, value in dataclasses.asdict(item).items()
    }


def print_comparison(
    rows: Sequence[CompensationMetrics], start: float, end: float, out: TextIO
) -> None:
    """The comparison table (thesis chapter 4 and section 1.2.4)."""
    print(
        "chapter 4 loop: G = 0.66 e^-2.6s/(6.7s+1), Gc = 0.1 + 0.09/s, "
        "He valve fs = 3, fd = 2, SP = 2",
        file=out,
    )
    print(f"compensators on from {start:g} s, judged from {start:g} to {end:g} s", file=out)
    print(
        "IAE: integral of |SP - PV|, % s; travel: valve travel, % of stroke; "
        "final |e|: mean |SP - PV| over the last tenth, %\n",
        file=out,
    )
    print(
        f"{'method':24s} {'IAE':>9s} {'travel':>9s} {'reversals':>9s} {'final |e|':>11s}",
        file=out,
    )
    for r in rows:
        print(
            f"{r.method:24s} {r.iae:9.1f} {r.valve_travel:9.1f} {r.valve_reversals:9d} "
            f"{r.final_pv_error:11.3f}",
            file=out,
        )


def _thesis(value: float, spec: str) -> str:
    return "-" if math.isnan(value) else format(value, spec)


def print_sensitivity(rows: Sequence[SensitivityRow], out: TextIO) -> None:
    """The sensitivity table beside thesis Tables 4.2-4.4."""
    print(
        "\nmodel-based compensator with estimated fs, fd, K (true 3, 2, 0.66; "
        "thesis Tables 4.2-4.4)",
        file=out,
    )
    print(
        f"{'fs':>5s} {'fd':>5s} {'K err':>6s} {'OP_ss':>7s} {'thesis':>7s} {'f1':>7s} "
        f"{'f2':>7s} {'|PV-SP| 1 move':>15s} {'thesis':>7s} {'repeated':>9s}",
        file=out,
    )
    for r in rows:
        print(
            f"{r.fs:5.2f} {r.fd:5.2f} {r.gain_error:+6.0%} {r.op_ss:7.2f} "
            f"{_thesis(r.thesis_op_ss, '7.2f'):>7s} {r.first_move:7.2f} {r.second_move:7.2f} "
            f"{r.pv_error_one_move:15.3f} {_thesis(abs(r.thesis_pv_error), '7.3f'):>7s} "
            f"{r.pv_error_repeated:9.3f}",
            file=out,
        )


def run(args: argparse.Namespace) -> int:
    """Handler of ``loopwatch compensate``."""
    try:
        comparison = compare_compensators(
            compensate_from=args.compensate_from, duration=args.duration
        )
        sensitivity = (
            () if args.no_sensitivity else model_based_sensitivity(switch_on_times=args.switch_on)
        )
    except AnalyticsError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(
            json.dumps(
                {
                    "comparison": [_row(r) for r in comparison],
                    "sensitivity": [_row(r) for r in sensitivity],
                },
                indent=2,
            )
        )
        return 0
    print_comparison(comparison, args.compensate_from, args.duration, sys.stdout)
    if sensitivity:
        print_sensitivity(sensitivity, sys.stdout)
    return 0

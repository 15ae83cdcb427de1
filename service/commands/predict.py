"""``loopwatch predict MODEL.json [--json]``: the limit cycles sticky valves will cause.

The describing-function prediction of every limit cycle (thesis Eqs. 3.14,
3.16 with ERRATA item 9; :func:`analytics.limit_cycle.predict_limit_cycles`)
beside the simulated ("exact") limit cycle of the same model and the error of
the prediction (:func:`analytics.limit_cycle.compare`).

The model file holds ``dt`` (the controllers' sampling period, s; its hold
counts as ``dt/2`` of dead time), ``process`` (one transfer function or
``{"matrix": n x n}``), ``controllers`` and ``valves`` (one per loop), and
optionally anything else :class:`analytics.simulation.ClosedLoopModel` reads
(``duration``, ``setpoints``, ``op_limits`` in a controller...). A loop without
a setpoint schedule gets a setpoint step for the simulation, and noise is left
out of it (:func:`analytics.tuning.excited_model`). Without ``duration`` the
simulation runs for 200 periods of the slowest predicted cycle (at least 2000 s,
at most 2 million samples).

``--json`` prints ``{"limit_cycles": [{"omega", "period_s", "amplitudes",
"stable", ...}], "linear_stable", "omega_range", "note", "simulated":
{"oscillating", "period_s", "amplitudes", ...}, "comparison": {...}}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

from analytics.limit_cycle import LimitCycleReport
from analytics.simulation import ClosedLoopModel
from service.commands import CliError, Subcommands, read_json_file
from service.prediction import ModelError, predict_spec


def register(commands: Subcommands) -> None:
    """Add ``predict`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser(
        "predict",
        help="predict the stiction limit cycles of a model and check them by simulation",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    parser.add_argument("model", type=Path, help="MODEL.json: dt, process, controllers, valves")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--omega-range",
        nargs=2,
        type=float,
        metavar=("LOW", "HIGH"),
        help="frequencies searched, rad/s (default: two decades around the crossover)",
    )
    parser.add_argument("--duration", type=float, help="simulated time, s")
    parser.set_defaults(handler=run)


def predict_file(
    path: Path,
    *,
    omega_range: tuple[float, float] | None = None,
    duration: float | None = None,
) -> tuple[ClosedLoopModel, LimitCycleReport]:
    """The model of ``path``, predicted and simulated (see :mod:`service.prediction`)."""
    try:
        return predict_spec(read_json_file(path), source=str(path), omega_range=omega_range,
                            duration=duration)
    except ModelError as exc:
        raise CliError(str(exc)) from None


def _number(value: float | None, spec: str = ".4g") -> str:
    return "-" if value is None else format(value, spec)


def print_report(
    report: LimitCycleReport, names: tuple[str, ...], source: str, out: TextIO
) -> None:
    """The readable form of ``loopwatch predict``."""
    prediction, simulated = report.prediction, report.simulated
    sticky = [names[i] for i, s in enumerate(prediction.sticky) if s]
    low, high = prediction.omega_range
    print(f"{source}: {len(names)} loop(s); sticky valves: {', '.join(sticky)}", file=out)
    print(f"describing functions: {prediction.note}", file=out)
    print(f"limit cycles predicted in {low:.4g}-{high:.4g} rad/s:", file=out)
    if not prediction.limit_cycles:
        print("  none", file=out)
    else:
        header = "".join(f"{'A ' + name:>11s}" for name in names)
        print(f"  {'omega rad/s':>11s} {'period s':>9s} {'stable':>7s}{header}", file=out)
        for cycle in prediction.limit_cycles:
            amplitudes = "".join(
                f"{_number(a) + ('' if moving else '*'):>11s}"
                for a, moving in zip(cycle.amplitudes, cycle.moving, strict=True)
            )
            stable = "yes" if cycle.stable else "no"
            print(f"  {cycle.omega:11.4g} {cycle.period_s:9.4g} {stable:>7s}{amplitudes}", file=out)
        if not all(all(cycle.moving) for cycle in prediction.limit_cycles):
            print("  (* the valve stays stuck: its OP amplitude is below the band)", file=out)
    start, end = simulated.window_s
    state = "oscillates" if simulated.oscillating else "no steady oscillation"
    note = f" ({simulated.note})" if simulated.note else ""
    print(f"simulation, analysed {start:g}-{end:g} s: {state}{note}", file=out)
    if simulated.oscillating:
        amplitudes = ", ".join(
            f"{name} {_number(a)}" for name, a in zip(names, simulated.amplitudes, strict=True)
        )
        print(f"  period {_number(simulated.period_s)} s; OP amplitude: {amplitudes}", file=out)
    if report.period_error_pct is not None:
        errors = ", ".join(
            f"{name} {e:+.1f} %"
            for name, e in zip(names, report.amplitude_error_pct, strict=True)
            if e is not None
        )
        print(
            f"describing function against the simulation: period {report.period_error_pct:+.1f} %"
            + (f"; amplitude {errors}" if errors else ""),
            file=out,
        )
    elif not report.agree:
        print("describing function and simulation disagree on whether the loop cycles", file=out)


def run(args: argparse.Namespace) -> int:
    """Handler of ``loopwatch predict``."""
    omega_range = None
    if args.omega_range:
        low, high = args.omega_range
        omega_range = (low, high)
    model, report = predict_file(args.model, omega_range=omega_range, duration=args.duration)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        names = tuple(loop.name for loop in model.loops)
        print_report(report, names, str(args.model), sys.stdout)
    return 0

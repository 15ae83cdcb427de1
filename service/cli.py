"""The ``loopwatch`` command line.

Commands that exist so far:

``loopwatch simulate NAME|MODEL.json [--out FILE] [--duration S]``
    Simulate a named scenario (``--list`` shows them) or a JSON model file
    (format: :class:`analytics.simulation.ClosedLoopModel`) and write the
    time series as CSV.
``loopwatch analyze FILE.csv [--ts S] [--time/--op/--pv/--sp/--mv COL]
[--process-type auto|self-regulating|integrating] [--json]``
    Diagnose one loop from measured data: data quality, oscillation,
    stiction verdict with the evidence of every method, and S/J estimates.
``loopwatch serve [--config PLANT.yaml] [--host H] [--port P] [--role api|ingest|scheduler|all]``
    Run the service: REST API, analyses, alarms and tickets.  Without a plant
    file it runs the simulated demo plant.
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

from analytics.diagnosis import LoopDiagnosis, diagnose_loop
from analytics.errors import AnalyticsError
from analytics.oscillation import detect_oscillations
from analytics.quality import QualityLimits
from analytics.scenarios import SCENARIOS, build_scenario
from analytics.simulation import ClosedLoopModel, SimulationResult
from service.commands import CliError, command_modules, read_json_file, read_loop_file


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


def _fmt(value: float | None, spec: str = ".3g") -> str:
    return "-" if value is None else format(value, spec)


def print_diagnosis(diagnosis: LoopDiagnosis, source: str, out: TextIO) -> None:
    """The readable report of ``loopwatch analyze``."""
    d = diagnosis
    print(f"{source}: {d.samples} samples at {d.ts:g} s", file=out)
    print(f"process type: {d.process_type or 'unknown'} ({d.process_type_source})", file=out)
    quality = "usable" if d.quality.usable else "UNUSABLE"
    print(f"data quality: {quality}", file=out)
    for issue in d.quality.issues:
        print(f"  [{issue.severity}] {issue.message}", file=out)
    osc = d.oscillation
    if osc is not None and osc.detected:
        print(
            f"oscillation: period {_fmt(osc.period_s, '.4g')} s, regularity "
            f"{_fmt(osc.regularity, '.3g')}, amplitude OP {_fmt(osc.amplitude_op)}, "
            f"PV {_fmt(osc.amplitude_pv)}",
            file=out,
        )
    elif osc is not None:
        print("oscillation: none found", file=out)
    v = d.stiction
    print(f"stiction: {v.verdict.upper()} (confidence {v.confidence:.2f}): {v.reason}", file=out)
    if d.pattern is not None:
        print(f"pattern: {d.pattern}", file=out)
    for episode in d.episodes:
        print(f"  episode: held {episode.start * d.ts:.0f}-{episode.jump_at * d.ts:.0f} s while "
              f"OP travelled {episode.op_travel:+.3g}, then PV jumped {episode.pv_jump:+.3g}",
              file=out)
    for name, e in v.methods.items():
        print(f"  {name:18s} {e.decision:12s} index {_fmt(e.index, '.3g'):>8s}  {e.note}", file=out)
    q = d.quantification
    if q is not None and q.S is not None:
        caveats = "" if q.trustworthy else f"  [not trustworthy: {'; '.join(q.issues)}]"
        print(
            f"stiction size (Hammerstein): S = {q.S:.2f}, J = {q.J:.2f}, fs = {q.fs:.2f}, "
            f"fd = {q.fd:.2f} (OP units), fit R2 = {q.fit_r2:.2f}{caveats}",
            file=out,
        )
    if d.episode_stick_band is not None:
        print(f"stick band from the episodes: {d.episode_stick_band:.2f} (OP units; between J "
              "and S: S after a reversal, J in the same direction)", file=out)
    if d.ellipse is not None:
        print(
            f"apparent stiction (ellipse fit): {d.ellipse.apparent_stiction:.2f} (OP units)",
            file=out,
        )


def _cmd_analyze(args: argparse.Namespace) -> int:
    data = read_loop_file(args, min_samples=QualityLimits().min_samples)
    process_type = None if args.process_type == "auto" else args.process_type
    try:
        diagnosis = diagnose_loop(
            ts=data.ts, op=data.op, pv=data.pv, sp=data.sp, mv=data.mv, t=data.t,
            process_type=process_type,
        )
    except AnalyticsError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    if args.json:
        print(json.dumps(diagnosis.to_dict(), indent=2, default=float))
    else:
        print_diagnosis(diagnosis, args.file, sys.stdout)
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
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
    analyze = commands.add_parser("analyze", help="diagnose one loop from a CSV file")
    analyze.add_argument("file", help="CSV with a header: time, op, pv (sp, mv optional)")
    analyze.add_argument("--ts", type=float, help="sampling interval in seconds")
    for column in ("time", "op", "pv", "sp", "mv"):
        analyze.add_argument(f"--{column}", help=f"name of the {column.upper()} column")
    analyze.add_argument(
        "--process-type",
        choices=("auto", "self-regulating", "integrating"),
        default="auto",
        help="process type (auto: unknown unless it can be inferred)",
    )
    analyze.add_argument("--json", action="store_true", help="print one JSON object")
    analyze.set_defaults(handler=_cmd_analyze)
    serve = commands.add_parser("serve", help="run the monitoring service (REST API)")
    serve.add_argument("--config", type=Path, help="plant YAML file (default: the demo plant)")
    serve.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port to listen on (default 8000)")
    serve.add_argument(
        "--role", choices=("api", "ingest", "scheduler", "all"),
        help="what this process runs (default all; see LOOPWATCH_ROLE): the API, the "
             "connectors of its ingest shard, the analysis scheduler (one leads, others "
             "stand by), or all of them",
    )
    serve.set_defaults(handler=_cmd_serve)
    demo = commands.add_parser("demo", help="simulate the thesis scenarios and summarise them")
    demo.set_defaults(handler=_cmd_demo)
    for module in command_modules():
        module.register(commands)
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

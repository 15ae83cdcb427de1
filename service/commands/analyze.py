"""``loopwatch analyze FILE.csv [--ts S] [--time/--op/--pv/--sp/--mv COL]
[--process-type auto|self-regulating|integrating] [--json]``.

Diagnoses one loop from measured data (:func:`analytics.diagnosis.diagnose_loop`):
data quality, oscillation, stiction verdict with the evidence of every
method, and S/J estimates.  The CSV is read by :func:`service.loop_csv.read_loop_csv`.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TextIO

from analytics.diagnosis import LoopDiagnosis, diagnose_loop
from analytics.errors import AnalyticsError
from analytics.quality import QualityLimits
from service.commands import CliError, Subcommands, read_loop_file

__all__ = ["print_diagnosis", "register"]


def register(commands: Subcommands) -> None:
    """Add ``analyze`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser("analyze", help="diagnose one loop from a CSV file")
    parser.add_argument("file", help="CSV with a header: time, op, pv (sp, mv optional)")
    parser.add_argument("--ts", type=float, help="sampling interval in seconds")
    for column in ("time", "op", "pv", "sp", "mv"):
        parser.add_argument(f"--{column}", help=f"name of the {column.upper()} column")
    parser.add_argument(
        "--process-type",
        choices=("auto", "self-regulating", "integrating"),
        default="auto",
        help="process type (auto: unknown unless it can be inferred)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=run)


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
    sized = d.episode_size
    if sized is not None and sized.S is not None:
        print(f"S from the episodes: {sized.S:.2f} (OP units; OP's travel from its turn to the "
              f"slip, median of {sized.reversals} after a reversal)", file=out)
    if d.size_comparison is not None:
        print(f"  {d.size_comparison.note}", file=out)
    if d.ellipse is not None:
        print(
            f"apparent stiction (ellipse fit): {d.ellipse.apparent_stiction:.2f} (OP units)",
            file=out,
        )


def run(args: argparse.Namespace) -> int:
    """Run ``loopwatch analyze``."""
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

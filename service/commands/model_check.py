"""``loopwatch model-check DATA.csv [--model MODEL.json] [--json]``.

Checks a loop model against measured data (:func:`analytics.model_check.check_model`):
what the simulation gets wrong, the cause, the extended model and the gain.
Without ``--model`` the model is identified from the data first.  The CSV
is read like ``loopwatch analyze`` reads it (:func:`service.loop_csv.read_loop_csv`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

import numpy as np

from analytics.errors import AnalyticsError
from analytics.model_check import MIN_SAMPLES, LoopModel, ModelCheck, check_model
from analytics.model_check.model import PROCESS_JSON_TYPES
from service.commands import CliError, Subcommands, read_json_file, read_loop_file

__all__ = ["print_report", "register"]


def _read_model(path: Path) -> LoopModel:
    spec = read_json_file(path)
    try:
        return LoopModel.from_dict(spec)
    except AnalyticsError as exc:
        raise CliError(f"{path}: {exc}") from None


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:+.0f} %"


def _num(x: float | None, spec: str = ".4g") -> str:
    return "-" if x is None else format(x, spec)


def print_report(result: ModelCheck, source: str, out: TextIO) -> None:
    """The readable report of ``loopwatch model-check``."""
    base = result.base_model
    p, c, v = base.process, base.controller.as_ideal(), base.valve.base
    valve = ", ".join(f"{k} = {x:.3g}" for k, x in v.to_dict().items() if k != "model")
    print(f"{source}: {result.overlay.t.size} samples at {base.dt:g} s", file=out)
    print(
        f"base model ({result.model_source}): {PROCESS_JSON_TYPES[p.kind]} K = {p.K:.4g}, "
        f"tau = {p.tau:.4g} s, "
        f"theta = {p.theta:.4g} s; PI Kc = {c.Kc:.4g}, Ti = {c.Ti:.4g} s; "
        f"{v.name} valve {valve}; op_bias = {base.op_bias:.4g} %",
        file=out,
    )
    cyc = result.cycle_base
    print(
        f"replay of the measured OP: held-out NMSE {result.nmse_base_test:.4g} "
        f"(noise floor about {result.noise_nmse:.2g})",
        file=out,
    )
    print(
        f"oscillation: measured period {_num(cyc.period_measured)} s, amplitude "
        f"{_num(cyc.amplitude_measured, '.3g')}; simulated {_num(cyc.period_simulated)} s, "
        f"{_num(cyc.amplitude_simulated, '.3g')}",
        file=out,
    )
    print("findings:", file=out)
    for finding in result.findings:
        print(f"  - {finding}", file=out)
    print("effects tried (held-out NMSE, share of the base model's error removed):", file=out)
    for cand in result.candidates:
        detail = cand.note or ", ".join(f"{k} = {x:.3g}" for k, x in cand.parameters.items())
        print(
            f"  {cand.effect:28s} {cand.nmse_test:10.4g} {100 * cand.improvement:+7.1f} %  "
            f"{detail}",
            file=out,
        )
    for i, cause in enumerate(result.causes):
        runner_up = f"; runner-up {cause.runner_up}" if cause.runner_up else ""
        print(
            f"{'cause' if i == 0 else 'second cause'}: {cause.effect} (confidence "
            f"{cause.confidence:.2f}{runner_up}; held-out NMSE {cause.nmse_before:.4g} -> "
            f"{cause.nmse_after:.4g})",
            file=out,
        )
    g = result.gain
    print(
        f"gain: held-out NMSE {g.nmse_before:.4g} -> {g.nmse_after:.4g}; period error "
        f"{_pct(g.before.period_error)} -> {_pct(g.after.period_error)}; amplitude error "
        f"{_pct(g.before.amplitude_error)} -> {_pct(g.after.amplitude_error)}",
        file=out,
    )
    print("extended model:", file=out)
    print(json.dumps(result.extended_model.to_dict(), indent=2), file=out)
    for note in result.notes:
        print(f"note: {note}", file=out)


def _run(args: argparse.Namespace) -> int:
    data = read_loop_file(args, min_samples=MIN_SAMPLES)
    if data.op is None or data.pv is None:
        missing = "op" if data.op is None else "pv"
        raise CliError(f"{args.file}: a model check needs both OP and PV; no {missing!r} column")
    steps = np.diff(data.t)
    irregular = np.flatnonzero(np.abs(steps - data.ts) > 0.01 * data.ts)
    if irregular.size:
        k = int(irregular[0])
        raise CliError(
            f"{args.file}: the sampling is irregular ({irregular.size} step(s) differ from "
            f"{data.ts:g} s, first between samples {k} and {k + 1}, t = {data.t[k]:g} and "
            f"{data.t[k + 1]:g} s); resample the data first"
        )
    model = _read_model(args.model) if args.model is not None else None
    try:
        result = check_model(data.op, data.pv, data.ts, sp=data.sp, model=model)
    except AnalyticsError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    if args.json:
        print(json.dumps(result.to_dict(overlay=args.overlay), indent=2))
    else:
        print_report(result, str(args.file), sys.stdout)
    return 0


def register(commands: Subcommands) -> None:
    """Add ``model-check`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser(
        "model-check",
        help="check a loop model against measured data, name the cause, extend it",
        description=__doc__.splitlines()[0] if __doc__ else None,
    )
    parser.add_argument("file", type=Path, help="CSV with a header: time, sp, op, pv (mv)")
    parser.add_argument("--model", type=Path, help="base model JSON (default: identify one)")
    parser.add_argument("--ts", type=float, help="sampling interval in seconds")
    for column in ("time", "op", "pv", "sp", "mv"):
        parser.add_argument(f"--{column}", help=f"name of the {column.upper()} column")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--overlay", action="store_true",
        help="with --json: add measured and simulated PV per sample (for plotting)",
    )
    parser.set_defaults(handler=_run)

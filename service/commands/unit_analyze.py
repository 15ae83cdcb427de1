"""``loopwatch unit-analyze FILE.csv [--loops LIST] [--model MODEL.json] [--skip S] [--ts S]
[--time COL] [--json]``.

Diagnoses a unit of interacting loops from one CSV file with a column
``op_<loop>`` and a column ``pv_<loop>`` for every loop (the columns that
``loopwatch simulate`` writes for a multi-loop model) and a time column:
the plant-wide oscillation groups, the number of sticky valves and which
ones (:func:`analytics.plantwide.diagnose_unit`).  With ``--model`` (the
model file of ``loopwatch predict``: ``process`` matrix and ``controllers``,
loops in the order of ``names`` or else of ``--loops``; its ``valves`` are
not used) the unit's own model tests every sticky set against the measured
cycle (:func:`analytics.plantwide.locate_sticky_valves`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

import numpy as np

from analytics.errors import AnalyticsError
from analytics.plantwide import GroupDiagnosis, UnitDiagnosis, UnitModel, diagnose_unit
from analytics.plantwide.unit import MODEL_NOTE
from analytics.simulation import ClosedLoopModel
from analytics.types import FloatArray
from connectors.base import read_csv_rows
from service.commands import CliError, Subcommands, read_json_file, read_loop_file
from service.loop_csv import LoopCsvError

__all__ = ["print_unit_diagnosis", "register", "run"]


def register(commands: Subcommands) -> None:
    """Add the ``unit-analyze`` subcommand to ``commands`` (an ``add_subparsers()`` object)."""
    parser = commands.add_parser(
        "unit-analyze", help="find the sticky valves of a unit of interacting loops (CSV)"
    )
    parser.add_argument("file", help="CSV with a time column and op_<loop>, pv_<loop> columns")
    parser.add_argument(
        "--loops", help="comma-separated loop names (default: every op_/pv_ pair in the file)"
    )
    parser.add_argument(
        "--skip", type=float, default=0.0,
        help="seconds at the start of the file to leave out (e.g. a start-up transient)",
    )
    parser.add_argument(
        "--model", help="model file of the unit (process matrix and controllers, as for predict)"
    )
    parser.add_argument("--ts", type=float, help="sampling interval in seconds")
    parser.add_argument("--time", help="name of the time column")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=run)


def _header(path: Path) -> list[str]:
    """The column names, read as the loops' data will be (commas or semicolons, a BOM)."""
    try:
        return read_csv_rows(path, LoopCsvError)[0]
    except LoopCsvError as exc:
        raise CliError(str(exc)) from None


def _loop_names(path: Path, wanted: str | None) -> list[str]:
    """The loops asked for, or every name with both an ``op_`` and a ``pv_`` column."""
    if wanted is not None:
        names = [name.strip() for name in wanted.split(",")]
        if not all(names):
            raise CliError(f"--loops {wanted!r} has an empty loop name")
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise CliError(f"--loops names {', '.join(duplicates)} more than once")
        return names
    columns = {h.strip().lower() for h in _header(path)}
    names = sorted(c[3:] for c in columns if c.startswith("op_") and f"pv_{c[3:]}" in columns)
    if not names:
        raise CliError(f"{path}: no pair of op_<loop> and pv_<loop> columns; give --loops")
    return names


def _read_loop(
    path: Path, loop: str, args: argparse.Namespace
) -> tuple[float, FloatArray, FloatArray]:
    """Sampling interval, OP and PV of ``loop``; missing values are refused."""
    data = read_loop_file(args, context=f"loop {loop}: ", op=f"op_{loop}", pv=f"pv_{loop}")
    assert data.op is not None and data.pv is not None  # both columns were named
    for role, values in (("op", data.op), ("pv", data.pv)):
        missing = np.flatnonzero(~np.isfinite(values))
        if missing.size:
            raise CliError(
                f"{path}, column '{data.columns[role]}': {missing.size} missing value(s), the "
                f"first in data row {missing[0] + 1}; the unit analysis needs complete data"
            )
    kept = data.t >= args.skip
    return data.ts, data.op[kept], data.pv[kept]


def run(args: argparse.Namespace) -> int:
    """Handler of ``loopwatch unit-analyze``."""
    path = Path(args.file)
    if not (np.isfinite(args.skip) and args.skip >= 0):
        raise CliError(f"--skip must be a number of seconds >= 0, got {args.skip}")
    names = _loop_names(path, args.loops)
    data = {loop: _read_loop(path, loop, args) for loop in names}
    ts = data[names[0]][0]
    model = None if args.model is None else _unit_model(Path(args.model), names)
    try:
        diagnosis = diagnose_unit({loop: (op, pv) for loop, (_, op, pv) in data.items()}, ts,
                                  model=model)
    except AnalyticsError as exc:
        raise CliError(f"{path}: {exc}") from None
    if args.json:
        print(json.dumps(diagnosis.to_dict(), indent=2, default=float))
    else:
        print_unit_diagnosis(diagnosis, str(path), sys.stdout)
    return 0


def _unit_model(path: Path, names: list[str]) -> UnitModel:
    """The process matrix and controllers of a ``predict`` model file, as a unit model."""
    spec = read_json_file(path)
    if not isinstance(spec, dict):
        raise CliError(f"{path}: a model must be a JSON object")
    spec = {"valves": [{"model": "ideal"}] * len(spec.get("controllers") or []), **spec}
    try:
        model = ClosedLoopModel.from_dict(spec)
    except (AnalyticsError, KeyError, TypeError, ValueError) as exc:
        raise CliError(f"{path}: {exc}") from None
    matrix = model.process if isinstance(model.process, tuple) else ((model.process,),)
    loops = tuple(spec["names"]) if "names" in spec else tuple(names)
    if len(loops) != len(matrix):
        raise CliError(f"{path}: the model has {len(matrix)} loops, the unit {len(loops)} "
                       f"({', '.join(loops)}); list them in the model's 'names'")
    unknown = [loop for loop in loops if loop not in names]
    if unknown:
        raise CliError(f"{path}: the model's loops {unknown} are not among the unit's "
                       f"({', '.join(names)})")
    return UnitModel(loops, matrix, tuple(loop.controller for loop in model.loops))


def _print_group(group: GroupDiagnosis, out: TextIO) -> None:
    print(f"  period {group.period_s:.4g} s ({group.cycles:.1f} cycles), loops: "
          f"{', '.join(group.loops) or 'none'}", file=out)
    members = ", ".join(f"{m.signal} ({m.power_fraction:.0%})" for m in group.members)
    print(f"    signals (share of variance): {members}", file=out)
    d = group.decomposition
    if d is not None:
        structures = "; ".join(f"{name} = {' + '.join(s)}" for name, s in d.structures.items())
        errors = ", ".join(f"{e:.3f}" for e in d.held_out_error)
        print(f"    shapes (thesis step 2): k = {d.k} of {d.n}; held-out error for "
              f"k = 0..{len(d.held_out_error) - 1}: {errors}", file=out)
        print(f"      {structures}", file=out)
    if group.ranking:
        ranking = ", ".join(f"{signal} {n:.2f}" for signal, n in group.ranking)
        print(f"    nonlinearity ranking (thesis step 3): {ranking}", file=out)
    for e in group.evidence:
        mark = "STICKY" if e.sticky else "ok"
        print(f"    {e.loop:>12s} {mark:6s} {e.note}", file=out)
    print(f"    -> {group.note}", file=out)


def print_unit_diagnosis(diagnosis: UnitDiagnosis, source: str, out: TextIO) -> None:
    """The readable report of ``loopwatch unit-analyze``."""
    d = diagnosis
    print(f"{source}: {len(d.loops)} loops ({', '.join(d.loops)}), {d.samples} samples at "
          f"{d.ts:g} s", file=out)
    if d.sticky_valves:
        print(f"sticky valves: k = {d.k}", file=out)
        for f in d.sticky_valves:
            size = "" if f.S is None else f", S = {f.S:.2f}, J = {f.J:.2f}"
            print(f"  {f.loop}: confidence {f.confidence:.2f} (cycle of {f.period_s:.4g} s"
                  f"{size})", file=out)
    else:
        print("sticky valves: none found (k = 0)", file=out)
    print(f"model: {'none; ' if d.linear is None else ''}"
          f"{MODEL_NOTE if d.linear is None else d.linear.note}", file=out)
    if not d.groups:
        print("oscillation groups: none; no loop oscillates", file=out)
        return
    print("oscillation groups:", file=out)
    for group in d.groups:
        _print_group(group, out)

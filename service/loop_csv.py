"""Reading one loop's measured data from a CSV file.

The file is read as the replay connector reads a historian export
(:func:`connectors.replay.read_historian_export`): a header row, commas or
semicolons with decimal commas, a byte-order mark ignored, rows in any order
(historian exports run newest first), time as one column (``time``, ``t``,
``t_s``, ``timestamp``: seconds or ISO 8601, UTC unless an offset is given)
or as ``date`` and ``time`` columns.  Signal columns are found by name,
case-insensitively: ``op``, ``pv``, ``sp`` and ``mv``; any of them can be
named explicitly instead.  Without a time column the sampling interval must
be given.  Empty cells, ``nan`` and ``NULL`` are kept as missing values (NaN)
for the data-quality screen to report; anything else that is not a number is
refused with the row and column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analytics.types import FloatArray
from connectors.replay import read_historian_export

__all__ = ["LoopCsvError", "LoopData", "read_loop_csv"]


SIGNALS = ("op", "pv", "sp", "mv")

TS_TOLERANCE = 0.01
"""Relative difference between ``ts`` and the time column's median step that is warned of."""


class LoopCsvError(ValueError):
    """The CSV cannot be read as loop data; the message names file, row and column."""


@dataclass(frozen=True)
class LoopData:
    """Measured signals of one loop, in time order; signals absent from the file are None."""

    t: FloatArray
    ts: float
    op: FloatArray | None
    pv: FloatArray | None
    sp: FloatArray | None
    mv: FloatArray | None
    columns: dict[str, str]  # signal -> column name used ("time": the time column(s))
    warnings: tuple[str, ...] = ()
    """Where the options and the data disagree (the data won)."""

    @property
    def samples(self) -> int:
        """Number of rows read."""
        return int(self.t.size)


def read_loop_csv(
    path: str | Path,
    *,
    ts: float | None = None,
    time: str | None = None,
    op: str | None = None,
    pv: str | None = None,
    sp: str | None = None,
    mv: str | None = None,
    min_samples: int = 2,
) -> LoopData:
    """Read ``path`` as loop data (see the module docstring).

    Parameters
    ----------
    ts : float, optional
        Sampling interval in seconds; required when the file has no time
        column.  With a time column whose median step differs from it, the
        time column's step is used and a warning says so.
    time, op, pv, sp, mv : str, optional
        Column names to use instead of the default names.
    min_samples : int
        Fewest data rows accepted.

    Raises
    ------
    LoopCsvError
        Missing file or columns, a cell that is not a number (with its row
        and column), too few rows, or two rows with the same time.
    """
    path = Path(path)
    if ts is not None and not (math.isfinite(ts) and ts > 0):
        raise LoopCsvError(f"--ts must be a positive number of seconds, got {ts}")
    named = {name: column for name, column in
             {"op": op, "pv": pv, "sp": sp, "mv": mv}.items() if column is not None}
    export = read_historian_export(
        path, list(named.values()), optional=[s for s in SIGNALS if s not in named],
        time_column=time, interval=ts, error=LoopCsvError)
    by_signal = {name: named.get(name, name) for name in SIGNALS}
    values = {name: export.values.get(column) for name, column in by_signal.items()}
    if values["op"] is None and values["pv"] is None:
        raise LoopCsvError(f"{path}: needs an 'op' or a 'pv' column (or --op/--pv)")
    if export.times.size < max(min_samples, 2):
        raise LoopCsvError(
            f"{path}: {export.times.size} data rows, at least {max(min_samples, 2)} are needed"
        )
    t = export.times - export.times[0]
    step = float(np.median(np.diff(t)))
    warnings = []
    if ts is None or (export.time_columns and abs(step - ts) > TS_TOLERANCE * ts):
        if ts is not None:
            warnings.append(
                f"--ts {ts:g} s disagrees with the time column "
                f"({' and '.join(export.time_columns)}: median step {step:g} s); the time "
                "column is used (leave out --ts, or name another time column with --time)")
        ts = step
    columns = {name: export.columns[column] for name, column in by_signal.items()
               if column in export.columns}
    if export.time_columns:
        columns["time"] = " and ".join(export.time_columns)
    return LoopData(
        t=t,
        ts=float(ts),
        op=values["op"],
        pv=values["pv"],
        sp=values["sp"],
        mv=values["mv"],
        columns=columns,
        warnings=tuple(warnings),
    )

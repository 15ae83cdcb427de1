"""Reading one loop's measured data from a CSV file.

The file has a header row; columns are found by name, case-insensitively:
time (``time``, ``t``, ``t_s``, ``timestamp``), ``op``, ``pv``, ``sp`` and
``mv``; any of them can be named explicitly instead.  Time is either seconds
(any numeric column) or ISO 8601 timestamps (UTC unless an offset is
given); without a time column the sampling interval must be given.  Empty
cells and ``nan`` are kept as missing values (NaN) for the data-quality
screen to report; anything else that is not a number is refused with the
row and column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from connectors.base import TIME_NAMES, column_index, number_columns, parse_time, read_csv_rows

__all__ = ["LoopCsvError", "LoopData", "read_loop_csv"]

FloatArray = NDArray[np.float64]

SIGNALS = ("op", "pv", "sp", "mv")


class LoopCsvError(ValueError):
    """The CSV cannot be read as loop data; the message names file, row and column."""


@dataclass(frozen=True)
class LoopData:
    """Measured signals of one loop; signals absent from the file are None."""

    t: FloatArray
    ts: float
    op: FloatArray | None
    pv: FloatArray | None
    sp: FloatArray | None
    mv: FloatArray | None
    columns: dict[str, str]  # signal -> column name used

    @property
    def samples(self) -> int:
        """Number of rows read."""
        return int(self.t.size)


def _find(header: list[str], wanted: str | None, names: tuple[str, ...], path: Path) -> int | None:
    if wanted is not None:
        return column_index(header, wanted, path, LoopCsvError)
    lowered = [h.strip().lower() for h in header]
    for name in names:
        if name in lowered:
            return lowered.index(name)
    return None


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
        column, and when given with a time column it is the nominal interval
        (the time column is still checked).
    time, op, pv, sp, mv : str, optional
        Column names to use instead of the default names.
    min_samples : int
        Fewest data rows accepted.

    Raises
    ------
    LoopCsvError
        Missing file or columns, a cell that is not a number (with its row
        and column), too few rows, or time that does not increase.
    """
    path = Path(path)
    if ts is not None and not (math.isfinite(ts) and ts > 0):
        raise LoopCsvError(f"--ts must be a positive number of seconds, got {ts}")
    header, body = read_csv_rows(path, LoopCsvError)
    wanted = {"op": op, "pv": pv, "sp": sp, "mv": mv}
    index = {name: _find(header, wanted[name], (name,), path) for name in SIGNALS}
    time_index = _find(header, time, TIME_NAMES, path)
    if index["op"] is None and index["pv"] is None:
        raise LoopCsvError(
            f"{path}: needs an 'op' or a 'pv' column (or --op/--pv); "
            f"the header has {', '.join(header)}"
        )
    if time_index is None and ts is None:
        raise LoopCsvError(
            f"{path}: no time column (time, t, t_s, timestamp); give --time or --ts"
        )
    used = {name: i for name, i in index.items() if i is not None}
    values = number_columns(path, header, body, used, LoopCsvError)
    t: FloatArray = np.empty(len(body))
    for k, (number, row) in enumerate(body):
        if time_index is not None:
            try:
                t[k] = parse_time(row[time_index])
            except ValueError:
                raise LoopCsvError(
                    f"{path}, row {number}, column {header[time_index]!r}: "
                    f"{row[time_index]!r} is neither seconds nor an ISO 8601 time"
                ) from None
    if time_index is None:
        assert ts is not None
        t = np.arange(len(body), dtype=np.float64) * ts
    else:
        steps = np.diff(t)
        bad = np.flatnonzero(~(steps > 0))
        if bad.size:
            k = int(bad[0])
            raise LoopCsvError(
                f"{path}, row {body[k + 1][0]}: time {t[k + 1]:g} does not increase "
                f"(previous row {body[k][0]} has {t[k]:g}); sort the file and remove duplicates"
            )
        t = t - t[0]
    if len(body) < max(min_samples, 2):
        raise LoopCsvError(
            f"{path}: {len(body)} data rows, at least {max(min_samples, 2)} are needed"
        )
    if ts is None:
        ts = float(np.median(np.diff(t)))
    return LoopData(
        t=t,
        ts=float(ts),
        op=values.get("op"),
        pv=values.get("pv"),
        sp=values.get("sp"),
        mv=values.get("mv"),
        columns={name: header[i] for name, i in used.items()}
        | ({"time": header[time_index]} if time_index is not None else {}),
    )

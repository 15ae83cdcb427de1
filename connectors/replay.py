"""Replaying a historian CSV export into the service, at a chosen speed.

The export has a header row, one row per time and one column per signal,
separated by commas, or by semicolons with decimal commas
(:func:`connectors.base.read_csv_rows`); a byte-order mark is ignored.
Time is either one column (``time``, ``t``, ``t_s`` or ``timestamp``, or the
one named: UNIX seconds or ISO 8601) or a ``date`` column beside a ``time``
column (``2024-11-27`` and ``23:59:00``, as the plant exports in
``../shared/data/plant_unlabelled`` have).  Times without an offset are in
the given time zone (UTC unless told otherwise).  Rows may come in any order
(those exports run newest first): they are replayed in time order.

A row that is ``d`` seconds after the first is sent ``d / speed`` seconds
after the replay started, stamped with that moment (``timestamps="now"``:
the file's spacing divided by ``speed``, never in the future) or with its
own time (``timestamps="original"``).  Empty cells, ``nan`` and ``NULL``
are sent as bad samples; any other cell that is not a number, a time that cannot be
read, or two rows with the same time refuse the file with its row (the line
in the file, the header being row 1) and column.

:func:`read_historian_export` is also how ``loopwatch analyze`` and
``loopwatch model-check`` read a loop's file (``service.loop_csv``).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from connectors.base import (
    TIME_NAMES,
    BackgroundConnector,
    DeliveryCounters,
    SampleSink,
    column_index,
    hand_over,
    item,
    number_columns,
    parse_time,
    read_csv_rows,
)

__all__ = [
    "HistorianExport",
    "ReplayConnector",
    "ReplayConnectorConfig",
    "ReplayCounters",
    "ReplayError",
    "read_historian_export",
]

TimestampMode = Literal["now", "original"]


class ReplayError(ValueError):
    """The file cannot be replayed; the message names file, row and column."""


@dataclass(frozen=True)
class HistorianExport:
    """The columns to replay of one export, in time order.

    Attributes
    ----------
    times : ndarray
        UNIX seconds, strictly increasing (from 0 at the interval given when
        the file has no time column).
    values : dict
        column as asked for -> values (NaN where the cell was empty or ``nan``).
    rows : ndarray
        The file row of each time (the header is row 1).
    columns : dict
        column as asked for -> its name in the header.
    time_columns : tuple of str
        The header names the time was read from: one, ``date`` and ``time``,
        or none (rows at the given interval).
    """

    times: NDArray[np.float64]
    values: dict[str, NDArray[np.float64]]
    rows: NDArray[np.int64]
    columns: dict[str, str]
    time_columns: tuple[str, ...]


def _zone(name: str) -> ZoneInfo:
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise ValueError(f"unknown time zone {name!r} (use an IANA name such as 'UTC')") from None


def _time_columns(
    header: list[str], time_column: str | None, date_column: str | None, path: Path,
    error: type[ValueError],
) -> tuple[int | None, int | None]:
    """(date column or None, time column or None when the file has none) indices."""
    lowered = [h.strip().lower() for h in header]
    if date_column is None and time_column is None and "date" in lowered and "time" in lowered:
        date_column, time_column = "date", "time"
    if time_column is None:
        found = [name for name in TIME_NAMES if name in lowered]
        if not found:
            return None, None
        time_column = found[0]
    date_index = None if date_column is None else column_index(header, date_column, path, error)
    return date_index, column_index(header, time_column, path, error)


def _time_text(row: list[str], date_index: int | None, time_index: int) -> str:
    """A row's time as the file writes it (``DATE`` ``T`` ``TIME`` for two columns)."""
    text = row[time_index].strip()
    return text if date_index is None else f"{row[date_index].strip()}T{text}"


def _read_times(path: Path, header: list[str], body: list[tuple[int, list[str]]],
                date_index: int | None, time_index: int, zone: ZoneInfo,
                error: type[ValueError]) -> NDArray[np.float64]:
    """The UNIX time of every row, from a time column or a date and a time column."""
    times = np.empty(len(body))
    for k, (number, row) in enumerate(body):
        text = _time_text(row, date_index, time_index)
        try:
            times[k] = parse_time(text, zone)
        except ValueError:
            where = f"column {header[time_index]!r}" if date_index is None else (
                f"columns {header[date_index]!r} and {header[time_index]!r}"
            )
            raise error(
                f"{path}, row {number}, {where}: {text!r} is neither UNIX seconds "
                "nor an ISO 8601 time"
            ) from None
        if not math.isfinite(times[k]):
            raise error(f"{path}, row {number}, column {header[time_index]!r}: "
                        f"{text!r} is not a finite time")
    return times


def read_historian_export(
    path: str | Path,
    columns: Sequence[str],
    *,
    optional: Sequence[str] = (),
    time_column: str | None = None,
    date_column: str | None = None,
    timezone: str = "UTC",
    interval: float | None = None,
    error: type[ValueError] = ReplayError,
) -> HistorianExport:
    """Read ``columns`` of a historian export, sorted by time (see the module docstring).

    Parameters
    ----------
    columns : sequence of str
        Columns to read, by header name (case-insensitive).
    optional : sequence of str
        Columns read when the header has them.
    time_column, date_column : str, optional
        The time column (default: the first of :data:`TIME_NAMES`) and a
        date column beside it (default: ``date`` when there is a ``time``).
    interval : float, optional
        For a file without a time column: the seconds between rows (which
        then keep the file's order, from 0).  Without it such a file is refused.
    error : ValueError subclass
        What is raised.

    Raises
    ------
    error
        Missing file or column, a cell that is not a number or a time (with
        its row and column), a row of the wrong length, two rows with the
        same time, no time column and no ``interval``, or no data rows.
    """
    path = Path(path)
    try:
        zone = _zone(timezone)
    except ValueError as exc:
        raise error(f"{path}: {exc}") from None
    header, body = read_csv_rows(path, error)
    date_index, time_index = _time_columns(header, time_column, date_column, path, error)
    lowered = [h.strip().lower() for h in header]
    value_index = {name: column_index(header, name, path, error) for name in columns} | {
        name: lowered.index(name.strip().lower()) for name in optional
        if name.strip().lower() in lowered}
    clash = [name for name, i in value_index.items() if i in (date_index, time_index)]
    if clash:
        raise error(f"{path}: column {clash[0]!r} holds the time, it cannot be read as a signal")
    values = number_columns(path, header, body, value_index, error)
    numbers = np.array([number for number, _ in body], dtype=np.int64)
    found = {name: header[i] for name, i in value_index.items()}
    if time_index is None:
        if interval is None:
            raise error(
                f"{path}: no time column ({', '.join(TIME_NAMES)}, or date and time) in the "
                f"header ({', '.join(header)}); name it (time_column; --time on the command "
                "line) or give the sampling interval (--ts)")
        return HistorianExport(times=np.arange(len(body), dtype=np.float64) * interval,
                               values=values, rows=numbers, columns=found, time_columns=())
    times = _read_times(path, header, body, date_index, time_index, zone, error)
    order = np.argsort(times, kind="stable")
    times = times[order]
    rows = numbers[order]
    same = np.flatnonzero(np.diff(times) == 0)
    if same.size:
        # the time as the file gives it (seconds since start are no 1970 date)
        k = int(same[0])
        texts = list(dict.fromkeys(_time_text(body[i][1], date_index, time_index)
                                   for i in order[k:k + 2]))
        raise error(
            f"{path}, rows {rows[k]} and {rows[k + 1]}: the same time "
            f"{' and '.join(map(repr, texts))}; remove the duplicate"
        )
    used = tuple(header[i] for i in (date_index, time_index) if i is not None)
    return HistorianExport(times=times, values={name: v[order] for name, v in values.items()},
                           rows=rows, columns=found, time_columns=used)


class ReplayConnectorConfig(BaseModel):
    """A historian export to replay (the keys mirror :class:`ReplayConnector`'s arguments).

    Examples
    --------
    >>> config = ReplayConnectorConfig(path="FIC-211.csv", speed=60,
    ...                                columns={"FT_211": "FIC-211.PV", "FV_211": "FIC-211.OP"})
    >>> config.timestamps, config.timezone
    ('now', 'UTC')
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    path: Path
    columns: dict[str, str] = Field(min_length=1, description="file column -> tag")
    speed: float = Field(default=1.0, gt=0, description="file seconds per wall-clock second")
    timestamps: TimestampMode = "now"
    time_column: str | None = None
    date_column: str | None = None
    timezone: str = Field(default="UTC", description="time zone of times without an offset")
    max_rows_per_batch: int = Field(default=1000, ge=1)

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, timezone: str) -> str:
        _zone(timezone)
        return timezone

    @model_validator(mode="after")
    def _one_column_per_tag(self) -> ReplayConnectorConfig:
        seen: dict[str, str] = {}
        for column, tag in self.columns.items():
            if tag in seen:
                raise ValueError(
                    f"columns.{column}: tag {tag!r} is already fed by column {seen[tag]!r}"
                )
            seen[tag] = column
        return self


@dataclass(kw_only=True)
class ReplayCounters(DeliveryCounters):
    """What a :class:`ReplayConnector` has sent (one sample per row and column).

    Attributes
    ----------
    total_rows : int
        Rows of the file.
    rows : int
        File rows replayed so far.
    """

    total_rows: int
    rows: int = 0


class ReplayConnector(BackgroundConnector[ReplayCounters]):
    """Replay ``path`` into ``sink`` at ``speed`` times real time (see the module docstring).

    The file is read, checked and sorted when the connector is made, so a
    bad file fails at once.  ``await connector.run()`` returns when every
    row is sent (or when cancelled); :meth:`start` / :meth:`stop` run it in a
    thread of its own.  Rows due together go out in one batch of at most
    ``max_rows_per_batch`` rows, handed to the sink in a worker thread.  A
    stopped replay carries on where it stopped when run again.

    Parameters
    ----------
    path : path
        The CSV export.
    sink : SampleSink
        Receives ingest batches.
    columns : mapping
        File column -> tag to send it as.
    speed : float
        File seconds per wall-clock second (60: a minute of data per second).
    timestamps : {"now", "original"}
        Stamp each row with the moment it is due, or with its time in the file.
    time_column, date_column : str, optional
        Name the time column (and a date column before it) when they are
        not found by name.
    timezone : str
        IANA zone of times without an offset.
    max_rows_per_batch : int
        Most rows in one batch (bounds the sink's transactions at high speed).
    """

    def __init__(
        self,
        path: str | Path,
        sink: SampleSink,
        *,
        columns: Mapping[str, str],
        speed: float = 1.0,
        timestamps: TimestampMode = "now",
        time_column: str | None = None,
        date_column: str | None = None,
        timezone: str = "UTC",
        max_rows_per_batch: int = 1000,
    ) -> None:
        config = ReplayConnectorConfig(
            path=Path(path), columns=dict(columns), speed=speed, timestamps=timestamps,
            time_column=time_column, date_column=date_column, timezone=timezone,
            max_rows_per_batch=max_rows_per_batch,
        )
        export = read_historian_export(
            config.path, list(config.columns), time_column=time_column,
            date_column=date_column, timezone=timezone,
        )
        super().__init__(f"replay {config.path.name}",
                         ReplayCounters(total_rows=int(export.times.size)))
        self.config = config
        self.export = export
        self._sink = sink

    @classmethod
    def from_config(cls, config: ReplayConnectorConfig, sink: SampleSink) -> ReplayConnector:
        """The connector that ``config`` describes."""
        return cls(config.path, sink, **config.model_dump(exclude={"path"}))

    @property
    def finished(self) -> bool:
        """Whether every row has been sent and the sink has taken (or refused) all of
        it: rows are counted when their batch leaves, before the sink's worker thread
        has stored it."""
        counters = self._counters.snapshot()
        return counters.rows == counters.total_rows and counters.pending == 0

    async def run(self) -> None:
        """Send the rows not sent yet, each when it is due."""
        loop = asyncio.get_running_loop()
        times = self.export.times
        due = (times - times[0]) / self.config.speed  # seconds after the first row
        k = self._counters.rows  # a stopped replay carries on where it stopped
        if k == times.size:
            return
        start_wall = time.time() - due[k]  # read first: a stamp never runs ahead
        start = loop.time() - due[k]
        while k < times.size:
            await asyncio.sleep(due[k] - (loop.time() - start))
            end = int(np.searchsorted(due, loop.time() - start, side="right"))
            end = min(max(end, k + 1), k + self.config.max_rows_per_batch)
            stamps = start_wall + due[k:end] if self.config.timestamps == "now" else times[k:end]
            batch, bad = self._batch(k, end, stamps)
            await self._send(batch, bad=bad, rows=end - k)
            k = end

    def _batch(
        self, first: int, end: int, stamps: NDArray[np.float64]
    ) -> tuple[list[dict[str, Any]], int]:
        """The rows ``first`` to ``end`` as an ingest batch, and how many of its items are bad."""
        batch: list[dict[str, Any]] = []
        bad = 0
        for column, tag in self.config.columns.items():
            values = self.export.values[column][first:end]
            items = [
                item(float(stamp), None if math.isnan(value) else float(value))
                for stamp, value in zip(stamps, values, strict=True)
            ]
            bad += int(np.isnan(values).sum())
            batch.append({"tag": tag, "items": items})
        return batch, bad

    async def _send(self, batch: list[dict[str, Any]], bad: int, rows: int) -> None:
        with self._counters.lock:
            self._counters.rows += rows
            self._counters.samples += sum(len(entry["items"]) for entry in batch)
            self._counters.bad += bad
        await hand_over(self._sink, batch, self._counters, self.name)

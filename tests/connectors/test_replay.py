"""Replay of historian CSV exports: the plant exports in ../shared/data and malformed files."""

from __future__ import annotations

import asyncio
import csv
import itertools
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from connectors.replay import (
    ReplayConnector,
    ReplayConnectorConfig,
    ReplayError,
    read_historian_export,
)
from tests.shared_data import SHARED_DATA, require_file

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

PLANT = SHARED_DATA / "plant_unlabelled"
EXPORTS = {
    "FIC-211": ("FIC-211_20241121-27.csv", {"FT_211": "FIC-211.PV", "FV_211": "FIC-211.OP"}),
    "LIC-106": ("LIC-106_20241121-27.csv", {"FT_115": "LIC-106.PV", "LV_106": "LIC-106.OP"}),
}


class Sink:
    """Collects batches, noting when each arrived."""

    def __init__(self) -> None:
        self.batches: list[list[dict[str, Any]]] = []
        self.arrivals: list[float] = []

    def __call__(self, batch: list[dict[str, Any]]) -> None:
        self.batches.append(batch)
        self.arrivals.append(time.time())

    def items(self, tag: str) -> list[dict[str, Any]]:
        return [i for batch in self.batches for e in batch if e["tag"] == tag for i in e["items"]]


def file_rows(path: Path) -> list[dict[str, str]]:
    """The file's rows as the csv module reads them (an independent reading)."""
    with path.open(newline="", encoding="utf-8-sig") as handle:
        return list(csv.DictReader(handle))


def as_value(cell: str) -> float | None:
    return None if cell == "NULL" else float(cell)


@pytest.mark.parametrize("loop", sorted(EXPORTS))
def test_a_plant_export_replays_in_time_order_with_its_own_stamps(loop):
    name, columns = EXPORTS[loop]
    path = require_file(PLANT / name)
    rows = file_rows(path)
    sink = Sink()
    connector = ReplayConnector(path, sink, columns=columns, speed=1e6, timestamps="original")
    asyncio.run(connector.run())

    oldest, newest = rows[-1], rows[0]  # the export runs newest first
    for column, tag in columns.items():
        items = sink.items(tag)
        assert len(items) == len(rows) == 7 * 24 * 60  # one week at one minute
        stamps = [i["timestamp"] for i in items]
        first, last = (datetime.fromisoformat(f"{row['date']}T{row['time']}Z").timestamp()
                       for row in (oldest, newest))
        assert (stamps[0], stamps[-1]) == (first, last)
        assert {b - a for a, b in itertools.pairwise(stamps)} == {60.0}
        expected = [as_value(row[column]) for row in reversed(rows)]
        assert [i["value"] for i in items] == expected
        assert [i["good"] for i in items] == [v is not None for v in expected]
    counters = connector.counters
    nulls = sum(row[c] == "NULL" for row in rows for c in columns)
    assert counters.bad == nulls
    assert counters.samples == counters.delivered == 2 * len(rows)
    assert connector.finished


def test_restamped_replay_keeps_the_spacing_divided_by_speed_and_never_runs_ahead():
    name, columns = EXPORTS["FIC-211"]
    path = require_file(PLANT / name)
    speed = 60 * 5000.0  # a minute of data every 0.2 ms
    sink = Sink()
    connector = ReplayConnector(path, sink, columns=columns, speed=speed)
    started = time.time()
    asyncio.run(connector.run())
    stamps = [i["timestamp"] for i in sink.items("FIC-211.OP")]
    assert len(stamps) == 10080
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    # UNIX stamps near 1.7e9 s resolve to 2.4e-7 s
    assert min(steps) == pytest.approx(60 / speed, abs=1e-6)
    assert max(steps) == pytest.approx(60 / speed, abs=1e-6)
    assert started <= stamps[0]
    # no row is sent before its moment: every stamp is at most the batch's arrival time
    # (5 ms allow for the wall clock being slewed against the monotonic one the replay waits on)
    for batch, arrival in zip(sink.batches, sink.arrivals, strict=True):
        assert max(i["timestamp"] for e in batch for i in e["items"]) <= arrival + 0.005


def test_a_single_iso_time_column_with_missing_values(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text(
        "timestamp,FIC-1 PV,FIC-1 OP\n"
        "2024-05-01T12:00:02Z,3.0,\n"
        "2024-05-01T12:00:00Z,1.0,10\n"
        "2024-05-01T12:00:01+00:00,nan,11\n"
    )
    sink = Sink()
    connector = ReplayConnector(path, sink, columns={"FIC-1 PV": "PV", "FIC-1 OP": "OP"},
                                speed=1e3, timestamps="original")
    asyncio.run(connector.run())
    t0 = datetime(2024, 5, 1, 12, tzinfo=UTC).timestamp()
    assert sink.items("PV") == [
        {"timestamp": t0, "value": 1.0, "good": True},
        {"timestamp": t0 + 1, "value": None, "good": False},
        {"timestamp": t0 + 2, "value": 3.0, "good": True},
    ]
    assert [i["value"] for i in sink.items("OP")] == [10.0, 11.0, None]
    assert connector.counters.bad == 2


def test_unix_seconds_in_a_named_time_column(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("when,x\n1714564800,1\n1714564810.5,2\n")
    sink = Sink()
    connector = ReplayConnector(path, sink, columns={"x": "X"}, speed=1e3,
                                timestamps="original", time_column="when")
    asyncio.run(connector.run())
    assert [i["timestamp"] for i in sink.items("X")] == [1714564800.0, 1714564810.5]


def test_naive_times_are_read_in_the_given_time_zone(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("date,time,x\n2024-11-21,00:00:00,1\n2024-06-21,00:00:00,2\n")
    export = read_historian_export(path, ["x"], timezone="Europe/Berlin")
    # winter: UTC+1; summer: UTC+2 (and rows come out in time order)
    assert list(export.times) == [
        datetime(2024, 6, 20, 22, tzinfo=UTC).timestamp(),
        datetime(2024, 11, 20, 23, tzinfo=UTC).timestamp(),
    ]
    assert list(export.rows) == [3, 2]


@pytest.mark.parametrize(
    ("text", "columns", "message"),
    [
        ("date,time,x\n2024-11-21,00:00:00,1\n2024-11-21,00:01:00,1,5\n", ["x"],
         "row 3: 4 cells, the header has 3"),
        ("date,time,x\n2024-11-21,00:00:00,1\n2024-11-21,00:01:00,1O.5\n", ["x"],
         "row 3, column 'x': '1O.5' is not a number"),
        ("date,time,x\n2024-11-21,00:00:00,1\n2024-11-21,25:00:00,2\n", ["x"],
         "row 3, columns 'date' and 'time': '2024-11-21T25:00:00' is neither UNIX seconds"),
        ("t,x\n0,1\nyesterday,2\n", ["x"],
         "row 3, column 't': 'yesterday' is neither UNIX seconds nor an ISO 8601 time"),
        ("t,x\n5,1\n6,2\n5,3\n", ["x"], "rows 2 and 4: the same time"),
        ("t,x\n0,1\n", ["y"], "no column 'y'; the header has t, x"),
        ("a,x\n0,1\n", ["x"], "no time column (time, t, t_s, timestamp, or date and time)"),
        ("t,x\n0,1\n", ["t"], "column 't' holds the time, it cannot be read as a signal"),
        ("t,x\n", ["x"], "no data rows below the header"),
        ("", ["x"], "the file is empty"),
    ],
    ids=["cells", "number", "date-time", "time", "duplicate", "column", "no-time", "time-value",
         "no-rows", "empty"],
)
def test_malformed_files_are_refused_with_row_and_column(tmp_path, text, columns, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ReplayError) as caught:
        ReplayConnector(path, Sink(), columns=dict.fromkeys(columns, "TAG"))
    assert str(caught.value).startswith(str(path))
    assert message in str(caught.value)


def test_a_missing_or_binary_file_is_refused(tmp_path):
    with pytest.raises(ReplayError, match="no such file"):
        read_historian_export(tmp_path / "absent.csv", ["x"])
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ReplayError, match="not a text file"):
        read_historian_export(binary, ["x"])


def test_config_validation_names_the_key():
    with pytest.raises(ValidationError) as caught:
        ReplayConnectorConfig.model_validate(
            {"path": "x.csv", "columns": {"a": "T", "b": "T"}, "speed": 0, "timezone": "Mars/Base"}
        )
    errors = {e["loc"]: e["msg"] for e in caught.value.errors()}
    assert "greater than 0" in errors[("speed",)]
    assert "unknown time zone 'Mars/Base'" in errors[("timezone",)]
    with pytest.raises(ValidationError, match=r"columns\.b: tag 'T' is already fed by column 'a'"):
        ReplayConnectorConfig.model_validate({"path": "x.csv", "columns": {"a": "T", "b": "T"}})
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        ReplayConnectorConfig.model_validate({"path": "x.csv", "columns": {"a": "T"}, "loop": 1})


def wait_for(condition: Any) -> None:
    """Wait for ``condition`` (every 10 ms, at most 20 s: against hanging, not a speed check)."""
    for _ in range(2000):
        if condition():
            return
        time.sleep(0.01)
    raise AssertionError("timed out")


def test_from_config_in_a_thread_and_a_stopped_replay_carries_on_where_it_stopped(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("t,x\n" + "".join(f"{k},{k}\n" for k in range(200)))
    sink = Sink()
    config = ReplayConnectorConfig(path=path, columns={"x": "X"}, speed=100.0,
                                   max_rows_per_batch=10)
    connector = ReplayConnector.from_config(config, sink)
    connector.start()
    wait_for(lambda: connector.counters.rows >= 20)
    connector.stop()
    sent = connector.counters.rows
    assert 20 <= sent < 200
    assert not connector.finished and not connector.running
    connector.start()
    wait_for(lambda: connector.finished)
    connector.stop()
    values = [i["value"] for i in sink.items("X")]
    assert values == [float(k) for k in range(200)]  # nothing lost, nothing twice
    assert max(len(b[0]["items"]) for b in sink.batches) <= 10


def test_a_replay_is_finished_only_once_the_sink_has_stored_its_last_batch(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("t,x\n0,1\n1,2\n2,3\n")
    release = threading.Event()
    sink = Sink()

    def slow_sink(batch: list[dict[str, Any]]) -> None:
        release.wait(20)  # a database busy with the last batch
        sink(batch)

    connector = ReplayConnector(path, slow_sink, columns={"x": "X"}, speed=1e6,
                                max_rows_per_batch=3)
    connector.start()
    wait_for(lambda: connector.counters.rows == 3)  # every row has left the connector
    assert not connector.finished  # ... but the sink has not stored them yet
    release.set()
    wait_for(lambda: connector.finished)
    assert [i["value"] for i in sink.items("X")] == [1.0, 2.0, 3.0]
    connector.stop()


def test_a_failing_sink_is_counted(tmp_path):
    path = tmp_path / "export.csv"
    path.write_text("t,x\n0,1\n1,2\n2,3\n")

    def refuse(batch: list[dict[str, Any]]) -> None:
        raise RuntimeError("database is locked")

    connector = ReplayConnector(path, refuse, columns={"x": "X"}, speed=1e3)
    asyncio.run(connector.run())
    counters = connector.counters
    assert (counters.samples, counters.delivered, counters.undelivered) == (3, 0, 3)
    assert connector.finished
    asyncio.run(connector.run())  # a finished replay has nothing more to send
    assert connector.counters == counters

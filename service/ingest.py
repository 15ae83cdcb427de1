r"""Historian push: batches of samples for many tags, stored idempotently.

A batch has the shape of the PI Web API ``streamsets/recorded`` answer::

    [{"tag": "FIC101.PV", "items": [{"timestamp": "2024-05-01T12:00:00Z",
                                      "value": 12.5, "good": true}, ...]}, ...]

Every item is accounted for, per tag, so that ``received = stored +
already_stored + sum(refused)``:

``stored``
    Written now.  A NaN, infinite or null value, or ``good: false``, is stored
    as a *bad* sample (value NULL, good False) so analyses see the hole; those
    are also counted in ``bad``.
``already_stored``
    The store already holds the same sample (same value and quality): sending
    a batch twice stores nothing twice.
``refused``, by reason
    ``unknown_tag`` (the tag is not configured), ``bad_timestamp`` (neither
    UNIX seconds nor ISO 8601, not finite, or before 1970),
    ``future_timestamp`` (later than ``now + max_future_s``: a clock error or
    milliseconds sent as seconds), ``bad_value`` (a value sent as text, such
    as ``"NaN"`` or ``"12.5"``: the rest of the batch is stored all the same),
    ``duplicate_in_batch`` (the first item of a
    time stamp is kept) and ``conflict`` (the store holds a different value or
    quality for that time; stored samples are never changed).  The first
    refused items of a tag are listed with their time stamp as sent and the
    reason (``refused_items``).

Items of a tag that arrive out of time order are stored all the same and
counted in ``out_of_order``.  ISO time stamps without an offset are UTC.

A request body may also be a PI Web API ``GET streamsets/recorded`` answer as
PI sends it (:func:`from_pi_web_api`)::

    {"Links": {}, "Items": [{"WebId": "...", "Name": "FIC101.PV",
                             "Path": "\\\\PISRV01\\FIC101.PV",
                             "Items": [{"Timestamp": "2024-05-01T12:00:00.1234567Z",
                                        "Value": 12.5, "UnitsAbbreviation": "m3/h",
                                        "Good": true, "Questionable": false,
                                        "Substituted": false}, ...]}, ...]}

or its ``Items`` list alone.  A stream's tag is the plant file's ``pi_points``
entry of its ``Path``, else of its ``Name``, else the ``Name`` itself.  A
digital state (``"Value": {"Name": "Bad Input", "Value": 307, "IsSystem":
true}``) of the system set is stored as a bad sample, a state of the point's
own set as its code; ``Good: false`` is a bad sample; questionable and
substituted values are stored as the values PI shows.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections import Counter
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import lru_cache
from typing import Any, cast

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError
from sqlalchemy import CursorResult, TextualSelect, delete, func, select, text
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

from connectors.base import MISSING, TIME_NAMES
from service.store.models import IngestLog, Sample

__all__ = [
    "REFUSAL_REASONS",
    "IngestError",
    "IngestItem",
    "IngestReport",
    "NewSample",
    "PiStream",
    "PiStreams",
    "TagItems",
    "TagReport",
    "from_pi_web_api",
    "ingest_batch",
    "ingest_csv",
    "parse_batch",
    "parse_timestamp",
    "purge_samples",
]

log = logging.getLogger(__name__)

REFUSAL_REASONS = (
    "unknown_tag",
    "bad_timestamp",
    "future_timestamp",
    "bad_value",
    "duplicate_in_batch",
    "conflict",
)
INSERT_CHUNK = 1000  # rows per INSERT: 4,000 parameters, well inside both databases' limits
MAX_CSV_COLUMNS = 10_000
"""Columns of a CSV upload (a wide upload: one per tag)."""
MAX_REPORTED_ERRORS = 10
"""Problems of a malformed batch named in the error; the rest are counted."""

NewSample = tuple[float, float | None, bool]
"""A sample as stored: (time, value or None when bad, good)."""

StoredValues = dict[float, tuple[float | None, bool]]
"""One tag's samples in the store: time -> (value, good)."""

STAGE_TABLE = "loopwatch_ingest_stage"
"""PostgreSQL: the temporary table a batch is copied into before it is inserted."""


class IngestError(ValueError):
    """A batch or CSV upload that cannot be read at all; the message says where."""


class IngestItem(BaseModel):
    """One recorded value; strict, so a ``true`` is never taken for a time or a number."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)

    timestamp: str | float = Field(description="ISO 8601 (UTC without offset) or UNIX seconds")
    value: float | str | None = Field(
        description="null, NaN or infinite: stored as a bad sample; text (\"NaN\", \"12\") "
        "is refused, the item alone (bad_value)")
    good: bool = True


class TagItems(BaseModel):
    """The recorded values of one tag."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)

    tag: str = Field(min_length=1)
    items: list[IngestItem]


_BATCH = TypeAdapter(list[TagItems])


class PiDigitalState(BaseModel):
    """A digital state as PI Web API writes it in place of a value."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    Name: str
    Value: int = Field(description="the state's code in its set")
    IsSystem: bool = Field(default=False,
                           description="a state of the system set (Bad Input, Shutdown...)")


class PiTimedValue(BaseModel):
    """One recorded value of a PI Web API stream (other fields, as ``Annotated``, ignored)."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    Timestamp: str
    Value: float | PiDigitalState | None
    Good: bool = True
    Questionable: bool = False
    Substituted: bool = False
    UnitsAbbreviation: str | None = None


class PiStream(BaseModel):
    """The recorded values of one PI point or AF attribute, as PI Web API answers."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    WebId: str | None = None
    Name: str | None = None
    Path: str | None = None
    Items: list[PiTimedValue]


class PiStreams(BaseModel):
    """A PI Web API ``streamsets/recorded`` answer (``Links`` ignored)."""

    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    Items: list[PiStream]


_PI_STREAMS = TypeAdapter(list[PiStream])


class TagReport(BaseModel):
    """What happened to the items of one tag.

    ``first_timestamp`` and ``last_timestamp`` bound the tag's items that are
    in the store after the call (stored or already stored); None if none are.
    The ingest response's per-tag report
    (:class:`service.api.schemas.ingest.TagIngest`): a field's docstring is its
    OpenAPI description.
    """

    model_config = ConfigDict(frozen=True, use_attribute_docstrings=True)

    tag: str
    received: int
    stored: int
    """Samples written."""
    already_stored: int
    """Items the store already held with the same value."""
    bad: int
    """Bad samples written (NaN, null or ``good: false``)."""
    out_of_order: int
    """Items that came after a later one of the same tag."""
    refused: dict[str, int]
    """Refused items by reason: ``unknown_tag``, ``bad_timestamp``, ``future_timestamp``,
    ``bad_value`` (a value sent as text), ``duplicate_in_batch``, ``conflict``."""
    first_timestamp: float | None
    """First of the tag's items in the store after the call, UNIX s; null if none is."""
    last_timestamp: float | None
    """Last of them, UNIX s."""
    refused_items: list[dict[str, Any]] = Field(default_factory=list)
    """The first :data:`MAX_REPORTED_ERRORS` refused items: ``timestamp`` as sent and
    ``reason``."""


@dataclass(frozen=True)
class IngestReport:
    """Per-tag reports, their totals, and the samples written (for the rolling buffers)."""

    tags: tuple[TagReport, ...]
    new_samples: dict[str, list[NewSample]] = field(repr=False)
    """Samples written by this call, per tag, in time order."""

    def _total(self, name: str) -> int:
        return sum(getattr(report, name) for report in self.tags)

    @property
    def received(self) -> int:
        """Items received, all tags."""
        return self._total("received")

    @property
    def stored(self) -> int:
        """Samples written, all tags."""
        return self._total("stored")

    @property
    def already_stored(self) -> int:
        """Items the store already held, all tags."""
        return self._total("already_stored")

    @property
    def bad(self) -> int:
        """Bad samples written, all tags."""
        return self._total("bad")

    @property
    def out_of_order(self) -> int:
        """Items that came after a later one of the same tag, all tags."""
        return self._total("out_of_order")

    @property
    def refused(self) -> dict[str, int]:
        """Refused items by reason, all tags."""
        total: Counter[str] = Counter()
        for report in self.tags:
            total.update(report.refused)
        return {reason: total[reason] for reason in REFUSAL_REASONS if total[reason]}

    @property
    def partial(self) -> bool:
        """True when any item was refused (the API answers 207)."""
        return any(report.refused for report in self.tags)

    def as_dict(self) -> dict[str, Any]:
        """The JSON body of the ingest response: totals, then the per-tag reports."""
        return {
            "partial": self.partial,
            "received": self.received,
            "stored": self.stored,
            "already_stored": self.already_stored,
            "bad": self.bad,
            "out_of_order": self.out_of_order,
            "refused": self.refused,
            "tags": [report.model_dump() for report in self.tags],
        }


def parse_timestamp(raw: str | float) -> float | None:
    """UNIX seconds from UNIX seconds or an ISO 8601 string; None if not a valid time.

    >>> parse_timestamp("2024-05-01T12:00:00Z"), parse_timestamp("1714564800.5")
    (1714564800.0, 1714564800.5)
    >>> parse_timestamp("2024-05-01 14:00:00+02:00"), parse_timestamp("yesterday")
    (1714564800.0, None)
    """
    if isinstance(raw, str):
        text = raw.strip()
        try:
            seconds = float(text)
        except ValueError:
            try:
                stamp = datetime.fromisoformat(text)
            except ValueError:
                return None
            if stamp.tzinfo is None:
                stamp = stamp.replace(tzinfo=UTC)
            seconds = stamp.timestamp()
    else:
        seconds = float(raw)
    return seconds if math.isfinite(seconds) and seconds >= 0 else None


class _TagIngest:
    """The accounting of one tag's items while a batch is ingested."""

    def __init__(self, tag: str) -> None:
        self.tag = tag
        self.received = 0
        self.already_stored = 0
        self.out_of_order = 0
        self.newest = -math.inf  # latest valid time stamp so far, to count out-of-order items
        self.refused: Counter[str] = Counter()
        self.refused_items: list[dict[str, Any]] = []
        self.in_store: list[float] = []  # times stored or already stored
        self.new: dict[float, tuple[float | None, bool]] = {}  # time -> (value, good) to write
        self.written: list[NewSample] = []

    def take(self, items: Sequence[IngestItem], *, known: bool, latest: float) -> None:
        """Screen the items; keep the first one of each valid time stamp in arrival order."""
        self.received += len(items)
        if not known:
            self.refused["unknown_tag"] += len(items)
            return
        for item in items:
            time = parse_timestamp(item.timestamp)
            value = item.value
            if isinstance(value, str):  # strict: text is no number, "NaN" and "12" alike
                self._refuse(item, "bad_value")
            elif time is None:
                self._refuse(item, "bad_timestamp")
            elif time > latest:
                self._refuse(item, "future_timestamp")
            elif time in self.new:
                self._refuse(item, "duplicate_in_batch")
            else:
                if time < self.newest:
                    self.out_of_order += 1
                self.newest = max(self.newest, time)
                good = item.good and value is not None and math.isfinite(value)
                self.new[time] = (value if good else None, good)

    def _refuse(self, item: IngestItem, reason: str) -> None:
        self.refused[reason] += 1
        if len(self.refused_items) < MAX_REPORTED_ERRORS:
            sent = item.timestamp  # as sent; JSON has no inf or NaN, so those as text
            if isinstance(sent, float) and not math.isfinite(sent):
                sent = str(sent)
            self.refused_items.append({"timestamp": sent, "reason": reason})

    def compare_with_store(self, session: Session, times: Collection[float]) -> None:
        """Move ``times`` the store already holds out of ``new``: same sample or conflict."""
        if times:
            self.resolve(times, _stored_values(session, {self.tag: times}).get(self.tag, {}))

    def resolve(self, times: Collection[float], stored: StoredValues) -> None:
        """Move ``times`` found in ``stored`` (the store's rows) out of ``new``."""
        for time in [t for t in times if t in stored]:
            if self.new.pop(time) == stored[time]:
                self.already_stored += 1
                self.in_store.append(time)
            else:
                self.refused["conflict"] += 1
                if len(self.refused_items) < MAX_REPORTED_ERRORS:
                    self.refused_items.append({"timestamp": time, "reason": "conflict"})

    def rows(self) -> list[dict[str, Any]]:
        """The rows to insert."""
        return [
            {"tag": self.tag, "time": time, "value": value, "good": good}
            for time, (value, good) in self.new.items()
        ]

    def settle(self, session: Session, inserted: set[tuple[str, float]],
               stored: StoredValues | None = None) -> None:
        """Account for the insert: rows another writer stored first are compared with the
        store (``stored``: the store's rows of those times, when already read)."""
        lost = [time for time in self.new if (self.tag, time) not in inserted]
        if stored is None:
            self.compare_with_store(session, lost)
        else:
            self.resolve(lost, stored)
        self.written = sorted((time, value, good) for time, (value, good) in self.new.items())
        self.in_store.extend(self.new)

    def report(self) -> TagReport:
        """The frozen report of this tag."""
        return TagReport(
            tag=self.tag,
            received=self.received,
            stored=len(self.written),
            already_stored=self.already_stored,
            bad=sum(1 for _, _, good in self.written if not good),
            out_of_order=self.out_of_order,
            refused={reason: n for reason in REFUSAL_REASONS if (n := self.refused[reason])},
            first_timestamp=min(self.in_store, default=None),
            last_timestamp=max(self.in_store, default=None),
            refused_items=self.refused_items,
        )


def _shape_error(exc: ValidationError, where: str) -> IngestError:
    """The first problems of a batch that does not validate, each with its place."""
    problems = "; ".join(
        where + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in e["loc"])
        + f": {e['msg']}"
        for e in exc.errors(include_url=False, include_input=False)[:MAX_REPORTED_ERRORS]
    )
    more = exc.error_count() - MAX_REPORTED_ERRORS
    return IngestError(f"invalid batch: {problems}" + (f" (and {more} more)" if more > 0 else ""))


def _validate(batch: Iterable[TagItems | dict[str, Any]]) -> list[TagItems]:
    try:
        return _BATCH.validate_python(list(batch))
    except ValidationError as exc:
        raise _shape_error(exc, "batch") from None
    except TypeError:
        raise IngestError("invalid batch: expected a list of {tag, items} objects") from None


def _is_pi_web_api(batch: Any) -> bool:
    """True for a PI Web API answer: ``{"Items": [...]}`` or a list of ``{"Items": ...}``."""
    if isinstance(batch, dict):
        return "Items" in batch
    return isinstance(batch, list) and any(
        isinstance(entry, dict) and "Items" in entry for entry in batch)


def _pi_value(value: PiTimedValue) -> dict[str, Any]:
    """An item of the simple shape from a PI Web API timed value."""
    number: float | None
    if isinstance(value.Value, PiDigitalState):
        number = None if value.Value.IsSystem else float(value.Value.Value)
    else:
        number = value.Value
    return {"timestamp": value.Timestamp, "value": number, "good": value.Good}


def from_pi_web_api(batch: Any, pi_points: Mapping[str, str]) -> list[TagItems]:
    """The simple shape of a PI Web API ``streamsets/recorded`` answer (module docstring).

    ``pi_points`` maps a stream's ``Path`` or ``Name`` to its tag (the plant
    file's ``pi_points``).

    Raises
    ------
    IngestError
        The answer does not have PI Web API's shape (a value that is neither
        a number nor a digital state, a stream with neither ``Name`` nor
        ``Path``...); the message names the place, as ``batch.Items[0].Items[3]``.
    """
    where = "batch.Items" if isinstance(batch, dict) else "batch"
    try:
        parsed = (PiStreams.model_validate(batch).Items if isinstance(batch, dict)
                  else _PI_STREAMS.validate_python(batch))
    except ValidationError as exc:
        raise _shape_error(exc, "batch") from None
    result = []
    for i, stream in enumerate(parsed):
        path = stream.Path or ""
        name = stream.Name or ""
        tag = pi_points.get(path) or pi_points.get(name) or name
        if not tag:
            raise IngestError(
                f"invalid batch: {where}[{i}]: a stream needs a Name or a Path to be mapped "
                f"to a tag (WebId {stream.WebId!r} alone names no tag)")
        result.append(TagItems(tag=tag, items=[IngestItem(**_pi_value(v)) for v in stream.Items]))
    return result


def parse_batch(body: bytes, *, max_samples: int,
                pi_points: Mapping[str, str] | None = None) -> list[TagItems]:
    """A JSON batch from a request body, refused in time bounded by ``max_samples``.

    The body is either the simple shape (a list of ``{tag, items}``) or a PI
    Web API answer (:func:`from_pi_web_api`, with ``pi_points``).  The
    entries and items are counted before anything is validated, so a batch
    of a million stray numbers costs a count, not a million errors; the
    error names the first :data:`MAX_REPORTED_ERRORS` problems and counts the
    others.  NaN and Infinity are read (some historians write them).

    Raises
    ------
    IngestError
        Not JSON, neither shape, or more than ``max_samples`` entries or items.
    """
    try:
        batch = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise IngestError(f"invalid batch: not JSON: {exc}") from None
    pi = _is_pi_web_api(batch)
    entries = batch.get("Items") if isinstance(batch, dict) else batch
    if not isinstance(entries, list):
        raise IngestError("invalid batch: expected a list of {tag, items} objects or a PI Web "
                          "API answer ({Items: [{Name, Path, Items: [...]}]})")
    key = "Items" if pi else "items"
    samples = sum(len(entry[key]) for entry in entries
                  if isinstance(entry, dict) and isinstance(entry.get(key), list))
    for what, count in (("entries", len(entries)), ("samples", samples)):
        if count > max_samples:
            raise IngestError(
                f"batch of {count} {what} is longer than the limit of {max_samples} "
                "(LOOPWATCH_MAX_BATCH_SAMPLES); split it")
    return from_pi_web_api(batch, pi_points or {}) if pi else _validate(entries)


TAGS_PER_LOOKUP = 100
"""Tags whose stored samples one statement reads (:func:`_stored_values`)."""


def _stored_values(session: Session, times: dict[str, Collection[float]]
                   ) -> dict[str, StoredValues]:
    """The samples the store holds of each tag between the first and the last of its
    ``times`` (a superset of those times), read in one statement per
    :data:`TAGS_PER_LOOKUP` tags: a statement per tag cost a batch of 50 tags more
    interpreter time than its insert."""
    ranges = [(tag, min(t), max(t)) for tag, t in times.items() if t]
    stored: dict[str, StoredValues] = {}
    for first in range(0, len(ranges), TAGS_PER_LOOKUP):
        chunk = ranges[first:first + TAGS_PER_LOOKUP]
        parameters = {f"{name}{k}": x for k, row in enumerate(chunk)
                      for name, x in zip(("t", "lo", "hi"), row, strict=True)}
        for tag, time, value, good in session.execute(_lookup(len(chunk)), parameters):
            stored.setdefault(tag, {})[time] = (value, good)
    return stored


@lru_cache(maxsize=TAGS_PER_LOOKUP)
def _lookup(tags: int) -> TextualSelect:
    """The statement of :func:`_stored_values` for ``tags`` tags, made once: building it
    from expressions for every batch cost more than running it."""
    ranges = " OR ".join(f"(tag = :t{k} AND time >= :lo{k} AND time <= :hi{k})"
                         for k in range(tags))
    return text(f"SELECT tag, time, value, good FROM {Sample.__tablename__} "
                f"WHERE {ranges}").columns(Sample.tag, Sample.time, Sample.value,
                                           Sample.good)


def _insert(session: Session, rows: list[dict[str, Any]]) -> set[tuple[str, float]]:
    """SQLite: insert ``rows``, skipping keys that exist; the (tag, time) keys actually
    inserted.

    Multi-row INSERTs of :data:`INSERT_CHUNK` rows whose parameters the driver binds:
    through SQLAlchemy's "insertmanyvalues" every row's parameters were processed in
    Python, a fifth of the server's interpreter time under the load benchmark
    (``benchmarks/load.py``), which the dashboard's requests waited for.
    """
    connection = session.connection()
    inserted: set[tuple[str, float]] = set()
    for start in range(0, len(rows), INSERT_CHUNK):
        chunk = rows[start:start + INSERT_CHUNK]
        result = connection.exec_driver_sql(
            f"INSERT INTO {Sample.__tablename__} (tag, time, value, good) VALUES "
            f"{', '.join(['(?, ?, ?, ?)'] * len(chunk))} "
            "ON CONFLICT DO NOTHING RETURNING tag, time",
            tuple(x for row in chunk for x in (row["tag"], row["time"], row["value"],
                                               row["good"])))
        inserted.update((tag, time) for tag, time in result)
    return inserted


def _copy_insert(
    session: Session, rows: list[dict[str, Any]]
) -> tuple[set[tuple[str, float]], dict[str, StoredValues]]:
    """PostgreSQL: COPY ``rows`` into a temporary table, insert what is new in one statement.

    Returns the (tag, time) keys inserted and, for the rows that were not, the
    values the store holds (per tag), read in one join.  COPY streams the
    batch with no statement or bound parameter per row: twice the rate of
    multi-row INSERTs, whose parameter lists the driver parses in Python
    (``benchmarks/scale.py``).
    """
    if not rows:
        return set(), {}
    connection = session.connection()
    connection.exec_driver_sql(
        f"CREATE TEMP TABLE IF NOT EXISTS {STAGE_TABLE} "
        "(tag varchar(200), time float8, value float8, good boolean) ON COMMIT DROP"
    )
    connection.exec_driver_sql(f"TRUNCATE {STAGE_TABLE}")
    driver: Any = connection.connection.driver_connection  # COPY is psycopg's own API
    with driver.cursor() as cursor, cursor.copy(
        f"COPY {STAGE_TABLE} (tag, time, value, good) FROM STDIN"
    ) as copy:
        for row in rows:
            copy.write_row((row["tag"], row["time"], row["value"], row["good"]))
    samples = Sample.__tablename__
    inserted = {(tag, time) for tag, time in connection.exec_driver_sql(
        f"INSERT INTO {samples} (tag, time, value, good) "
        f"SELECT tag, time, value, good FROM {STAGE_TABLE} "
        "ON CONFLICT DO NOTHING RETURNING tag, time"
    )}
    stored: dict[str, StoredValues] = {}
    if len(inserted) < len(rows):
        for tag, time, value, good in connection.exec_driver_sql(
            f"SELECT s.tag, s.time, s.value, s.good FROM {samples} s "
            f"JOIN {STAGE_TABLE} i ON s.tag = i.tag AND s.time = i.time"
        ):
            if (tag, time) not in inserted:
                stored.setdefault(tag, {})[time] = (value, good)
    return inserted, stored


def ingest_batch(
    session: Session,
    batch: Iterable[TagItems | dict[str, Any]],
    *,
    known_tags: Collection[str],
    now: float,
    max_future_s: float = 300.0,
) -> IngestReport:
    """Store a batch of samples of many tags (see the module docstring for the rules).

    Parameters
    ----------
    session : Session
        The transaction to write in; the caller commits.  Append
        ``report.new_samples`` to the rolling buffers only after the commit.
    batch : list of TagItems or of dicts of that shape
        A tag may appear more than once; its items are then taken in order.
    known_tags : collection of str
        Tags the store has (rows of ``tags``); items of others are refused.
    now : float
        Current UNIX time, s; items later than ``now + max_future_s`` are refused.

    Raises
    ------
    IngestError
        The batch does not have the expected shape (a missing ``tag``, a value
        that is not a number...); nothing is stored.
    """
    tags: dict[str, _TagIngest] = {}
    for entry in _validate(batch):
        tag = tags.setdefault(entry.tag, _TagIngest(entry.tag))
        tag.take(entry.items, known=entry.tag in known_tags, latest=now + max_future_s)
    if session.get_bind().dialect.name == "postgresql":
        # one COPY and one INSERT ... SELECT for the whole batch; what was not new is
        # then compared with the store, exactly as rows a concurrent writer stored first
        inserted, stored = _copy_insert(
            session, [row for tag in tags.values() for row in tag.rows()]
        )
        for tag in tags.values():
            tag.settle(session, inserted, stored.get(tag.tag, {}))
    else:
        stored = _stored_values(session, {tag.tag: list(tag.new) for tag in tags.values()})
        for tag in tags.values():
            if tag.new:
                tag.resolve(list(tag.new), stored.get(tag.tag, {}))
        inserted = _insert(session, [row for tag in tags.values() for row in tag.rows()])
        for tag in tags.values():
            tag.settle(session, inserted)
    written = [time for tag in tags.values() for time, _, _ in tag.written]
    if written:  # what schedulers in other processes read (service.scheduler.sync_buffers)
        session.add(IngestLog(received_at=now, first_time=min(written),
                              last_time=max(written), samples=len(written)))
    return IngestReport(
        tags=tuple(tag.report() for tag in tags.values()),
        new_samples={tag.tag: tag.written for tag in tags.values() if tag.written},
    )


_GOOD = {"": True, "1": True, "true": True, "good": True, "0": False, "false": False, "bad": False}


def _number(cell: str, where: str) -> float | None:
    text = cell.strip()
    if text in MISSING:
        return None
    try:
        return float(text)
    except ValueError:
        raise IngestError(f"{where}: {cell!r} is not a number") from None


def _csv_rows(text: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """The header and the non-blank data rows with their row numbers (header = row 1)."""
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff")), strict=True)
    try:
        rows = list(reader)
    except csv.Error as exc:
        raise IngestError(f"CSV line {reader.line_num}: not valid CSV: {exc}") from None
    if not rows:
        raise IngestError("CSV: the upload is empty")
    if not any(rows[0]):
        raise IngestError("CSV row 1: the header row is empty; the first line must name the "
                          "columns")
    if len(rows[0]) > MAX_CSV_COLUMNS:
        raise IngestError(f"CSV row 1: {len(rows[0])} columns, more than the limit of "
                          f"{MAX_CSV_COLUMNS}; split the upload")
    header = [name.strip() for name in rows[0]]
    body = [(number, row) for number, row in enumerate(rows[1:], start=2) if any(row)]
    for number, row in body:
        if len(row) != len(header):
            raise IngestError(f"CSV row {number}: {len(row)} cells, the header has {len(header)}")
    seen: set[str] = set()
    for i, name in enumerate(header, start=1):
        if not name:
            raise IngestError(f"CSV row 1, column {i}: empty column name")
        if name in seen:
            raise IngestError(f"CSV row 1, column {i}: duplicate column {name!r}")
        seen.add(name)
    return header, body


def _long_batch(header: list[str], body: list[tuple[int, list[str]]]) -> list[dict[str, Any]]:
    col: dict[str, int] = {}
    for i, name in enumerate(header):
        key = "timestamp" if name.lower() in TIME_NAMES else name.lower()
        if key not in ("tag", "timestamp", "value", "good"):
            raise IngestError(
                f"CSV row 1, column {i + 1}: unexpected column {name!r}; the long format has "
                "tag, timestamp (or time), value and optionally good"
            )
        if key in col:
            raise IngestError(f"CSV row 1, column {i + 1}: a second {key} column ({name!r})")
        col[key] = i
    missing = [key for key in ("timestamp", "value") if key not in col]
    if missing:
        raise IngestError(f"CSV row 1: the long format needs a {' and a '.join(missing)} column")
    items: dict[str, list[dict[str, Any]]] = {}
    for number, row in body:
        tag = row[col["tag"]].strip()
        if not tag:
            raise IngestError(f"CSV row {number}, column {header[col['tag']]!r}: empty tag")
        good = _GOOD.get(row[col["good"]].strip().lower()) if "good" in col else True
        if good is None:
            raise IngestError(
                f"CSV row {number}, column {header[col['good']]!r}: "
                f"{row[col['good']]!r} is not true/false, 1/0 or good/bad"
            )
        value = _number(row[col["value"]], f"CSV row {number}, column {header[col['value']]!r}")
        items.setdefault(tag, []).append(
            {"timestamp": row[col["timestamp"]], "value": value, "good": good}
        )
    return [{"tag": tag, "items": tag_items} for tag, tag_items in items.items()]


def _wide_batch(header: list[str], body: list[tuple[int, list[str]]]) -> list[dict[str, Any]]:
    if header[0].lower() not in TIME_NAMES:
        raise IngestError(
            f"CSV row 1, column 1: {header[0]!r} is not a time column; the wide format starts "
            f"with {'/'.join(TIME_NAMES)}, the long format has a tag column"
        )
    if len(header) < 2:
        raise IngestError("CSV row 1: the wide format needs at least one tag column")
    batch = []
    for i, tag in enumerate(header[1:], start=1):
        items = [
            {"timestamp": row[0], "value": _number(row[i], f"CSV row {number}, column {tag!r}")}
            for number, row in body
            if row[i].strip()
        ]
        batch.append({"tag": tag, "items": items})
    return batch


def ingest_csv(
    session: Session,
    text: str,
    *,
    known_tags: Collection[str],
    now: float,
    max_future_s: float = 300.0,
) -> IngestReport:
    """Store a CSV upload with the rules of :func:`ingest_batch`.

    Two layouts, told apart by a ``tag`` column:

    * long: columns ``tag``, ``timestamp`` (or ``time``), ``value`` and
      optionally ``good`` (true/false, 1/0, good/bad; empty = true), any order;
    * wide: a ``timestamp`` (or ``time``) column first, then one column per
      tag.  An empty cell means the tag has no sample at that time.

    A value of ``nan``, ``null`` or ``NA`` (and, in the long format, an empty
    value) is a bad sample.  Time stamps that cannot be read are refused per
    item (``bad_timestamp``) as in a JSON batch.

    Raises
    ------
    IngestError
        Malformed CSV: the message names the row (the header is row 1) and
        the column.
    """
    header, body = _csv_rows(text)
    batch = _long_batch(header, body) if "tag" in map(str.lower, header) else _wide_batch(
        header, body
    )
    return ingest_batch(
        session, batch, known_tags=known_tags, now=now, max_future_s=max_future_s
    )


def purge_samples(session: Session, older_than: float) -> int:
    """Delete the samples stamped before ``older_than`` (UNIX s); the number deleted.

    Where ``samples`` is a TimescaleDB hypertable (migration 0002), the chunks
    wholly before ``older_than`` are dropped with ``drop_chunks`` (a file
    removed, not millions of rows deleted and vacuumed), then the rest is
    deleted row by row; should ``drop_chunks`` fail, everything is deleted row
    by row as elsewhere.
    """
    if not math.isfinite(older_than):
        raise ValueError(f"older_than must be a finite UNIX time, got {older_than}")
    if _is_hypertable(session):
        count = session.scalar(select(func.count()).where(Sample.time < older_than)) or 0
        try:
            with session.begin_nested():  # a failure leaves the transaction usable
                session.execute(
                    text("SELECT drop_chunks('samples', older_than => CAST(:us AS bigint))"),
                    {"us": int(older_than * 1_000_000)})  # the partitioning unit (0002)
        except DBAPIError as exc:
            log.warning("drop_chunks failed (%s): old samples are deleted row by row",
                        type(exc).__name__)
        session.execute(delete(Sample).where(Sample.time < older_than))
        return int(count)
    result = session.execute(delete(Sample).where(Sample.time < older_than))
    return cast(CursorResult[Any], result).rowcount


def _is_hypertable(session: Session) -> bool:
    """True on PostgreSQL when TimescaleDB is installed and ``samples`` is its hypertable."""
    if session.get_bind().dialect.name != "postgresql" or session.scalar(
            text("SELECT 1 FROM pg_extension WHERE extname = 'timescaledb'")) is None:
        return False
    return session.scalar(text(
        "SELECT 1 FROM timescaledb_information.hypertables WHERE hypertable_name = 'samples'"
    )) is not None

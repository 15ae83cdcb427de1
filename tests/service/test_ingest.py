"""Historian ingest on SQLite and PostgreSQL: accounting, idempotency, CSV uploads, retention."""

import json
import math
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import delete, event, insert, select

from service.config import PlantConfig
from service.ingest import (
    INSERT_CHUNK,
    TAGS_PER_LOOKUP,
    IngestError,
    IngestReport,
    ingest_batch,
    ingest_csv,
    parse_timestamp,
    purge_samples,
)
from service.plant import sync_plant
from service.store.db import Store
from service.store.models import Sample

Row = tuple[str, float, float | None, bool]

NOW = 1_714_564_800.0  # 2024-05-01T12:00:00Z
PLANT = PlantConfig.model_validate(
    {"loops": [{"id": "FIC-101", "tags": {"op": "FIC101.OP", "pv": "FIC101.PV"}, "ts": 1.0}]}
)
KNOWN = {"FIC101.OP", "FIC101.PV"}


@pytest.fixture
def plant_store(store: Store) -> Store:
    """The store with loop FIC-101 and its tags FIC101.OP and FIC101.PV."""
    with store.session() as session:
        sync_plant(session, PLANT, NOW)
    return store


def ingest(store: Store, batch: Any, now: float = NOW) -> IngestReport:
    with store.session() as session:
        return ingest_batch(session, batch, known_tags=KNOWN, now=now)


def upload(store: Store, text: str) -> IngestReport:
    with store.session() as session:
        return ingest_csv(session, text, known_tags=KNOWN, now=NOW)


def stored(store: Store) -> list[Row]:
    """Every stored sample as (tag, time, value, good), sorted."""
    with store.session() as session:
        rows = session.execute(select(Sample.tag, Sample.time, Sample.value, Sample.good))
        return sorted((tag, time, value, good) for tag, time, value, good in rows)


def items(*samples: tuple[float | str, float | None]) -> list[dict[str, Any]]:
    return [{"timestamp": t, "value": v} for t, v in samples]


def balanced(report: IngestReport) -> bool:
    """The accounting invariant, per tag and in total."""
    for tag in report.tags:
        assert tag.received == tag.stored + tag.already_stored + sum(tag.refused.values())
    assert report.received == report.stored + report.already_stored + sum(report.refused.values())
    return True


def test_a_batch_is_stored_and_reported_per_tag(plant_store: Store) -> None:
    report = ingest(plant_store, [
        {"tag": "FIC101.PV", "items": items(("2024-05-01T11:59:58Z", 10.0), (NOW - 1, 10.5))},
        {"tag": "FIC101.OP", "items": items((NOW - 2, 40.0))},
    ])
    assert stored(plant_store) == [
        ("FIC101.OP", NOW - 2, 40.0, True),
        ("FIC101.PV", NOW - 2, 10.0, True),
        ("FIC101.PV", NOW - 1, 10.5, True),
    ]
    assert not report.partial
    assert (report.received, report.stored, report.already_stored) == (3, 3, 0)
    pv = report.tags[0]
    assert (pv.tag, pv.received, pv.stored, pv.refused) == ("FIC101.PV", 2, 2, {})
    assert (pv.first_timestamp, pv.last_timestamp) == (NOW - 2, NOW - 1)
    assert report.new_samples == {
        "FIC101.PV": [(NOW - 2, 10.0, True), (NOW - 1, 10.5, True)],
        "FIC101.OP": [(NOW - 2, 40.0, True)],
    }
    assert balanced(report)


def test_the_same_batch_twice_stores_nothing_twice(plant_store: Store) -> None:
    batch = [{"tag": "FIC101.PV", "items": [*items((NOW - 2, 1.0), (NOW - 1, None)),
                                            {"timestamp": NOW, "value": 3.0, "good": False}]}]
    first = ingest(plant_store, batch)
    rows = stored(plant_store)
    second = ingest(plant_store, batch)
    assert stored(plant_store) == rows
    assert (first.stored, first.bad, first.already_stored) == (3, 2, 0)
    assert (second.stored, second.bad, second.already_stored) == (0, 0, 3)
    assert not second.partial and second.new_samples == {}
    assert (second.tags[0].first_timestamp, second.tags[0].last_timestamp) == (NOW - 2, NOW)
    assert balanced(first) and balanced(second)


def test_unknown_tag_is_refused_whole_and_the_rest_is_stored(plant_store: Store) -> None:
    report = ingest(plant_store, [
        {"tag": "TIC999.PV", "items": items((NOW, 1.0), (NOW - 1, 2.0))},
        {"tag": "FIC101.PV", "items": items((NOW, 1.0))},
    ])
    unknown, pv = report.tags
    assert (unknown.received, unknown.stored, unknown.refused) == (2, 0, {"unknown_tag": 2})
    assert (unknown.first_timestamp, unknown.last_timestamp) == (None, None)
    assert pv.stored == 1 and report.partial and report.refused == {"unknown_tag": 2}
    assert stored(plant_store) == [("FIC101.PV", NOW, 1.0, True)]
    assert balanced(report)


def test_unparseable_and_future_timestamps_are_refused(plant_store: Store) -> None:
    report = ingest(plant_store, [{"tag": "FIC101.PV", "items": items(
        ("yesterday", 1.0), ("2024-13-01T00:00:00Z", 1.0), ("nan", 1.0), (-5.0, 1.0),
        (math.inf, 1.0),  # five bad time stamps
        (NOW * 1000, 1.0),  # milliseconds sent as seconds
        (NOW + 301, 1.0),  # beyond the 300 s allowed for clock skew
        (NOW + 299, 1.0),  # within it: stored
    )}])
    assert report.tags[0].refused == {"bad_timestamp": 5, "future_timestamp": 2}
    # each named as sent; an infinite one as text (JSON has no inf: the fuzz test's 500)
    assert [i["timestamp"] for i in report.tags[0].refused_items] == [
        "yesterday", "2024-13-01T00:00:00Z", "nan", -5.0, "inf", NOW * 1000, NOW + 301]
    json.dumps(report.as_dict(), allow_nan=False)
    assert stored(plant_store) == [("FIC101.PV", NOW + 299, 1.0, True)]
    assert balanced(report)


def test_nan_inf_null_and_flagged_values_are_stored_as_holes(plant_store: Store) -> None:
    report = ingest(plant_store, [{"tag": "FIC101.PV", "items": [
        *items((NOW - 5, math.nan), (NOW - 4, math.inf), (NOW - 3, -math.inf), (NOW - 2, None)),
        {"timestamp": NOW - 1, "value": 7.0, "good": False},
        {"timestamp": NOW, "value": 7.0, "good": True},
    ]}])
    assert [row[2:] for row in stored(plant_store)] == [(None, False)] * 5 + [(7.0, True)]
    assert (report.stored, report.bad, report.partial) == (6, 5, False)
    assert balanced(report)


def test_a_value_sent_as_text_is_refused_alone_with_its_time(plant_store: Store) -> None:
    """QA: one "NaN" (JSON has no NaN, so historians write it as text) made the whole
    batch a 422 and nothing was stored.  The item alone is refused (``bad_value``),
    named with its time stamp as sent; the rest is stored and the answer is partial."""
    report = ingest(plant_store, [
        {"tag": "FIC101.PV", "items": items((NOW - 2, 1.0), (NOW - 1, "NaN"), (NOW, "12"))},
        {"tag": "FIC101.OP", "items": items((NOW - 1, 40.0))}])
    pv = report.tags[0]
    assert (pv.stored, pv.refused, report.partial) == (1, {"bad_value": 2}, True)
    assert pv.refused_items == [{"timestamp": NOW - 1, "reason": "bad_value"},
                                {"timestamp": NOW, "reason": "bad_value"}]
    assert stored(plant_store) == [("FIC101.OP", NOW - 1, 40.0, True),
                                   ("FIC101.PV", NOW - 2, 1.0, True)]
    assert balanced(report)


def test_a_duplicate_time_in_a_batch_keeps_the_first_item(plant_store: Store) -> None:
    report = ingest(plant_store, [
        {"tag": "FIC101.PV", "items": items((NOW, 1.0), ("2024-05-01T12:00:00Z", 2.0))},
        {"tag": "FIC101.PV", "items": items(("2024-05-01T14:00:00+02:00", 3.0), (NOW - 1, 4.0))},
    ])
    assert len(report.tags) == 1  # a tag given twice is one tag
    assert report.tags[0].refused == {"duplicate_in_batch": 2}
    assert stored(plant_store) == [("FIC101.PV", NOW - 1, 4.0, True), ("FIC101.PV", NOW, 1.0, True)]
    assert balanced(report)


def test_a_different_value_for_a_stored_time_is_a_conflict_and_changes_nothing(
    plant_store: Store,
) -> None:
    ingest(plant_store, [{"tag": "FIC101.PV", "items": items((NOW - 2, 1.0), (NOW - 1, None))}])
    report = ingest(plant_store, [{"tag": "FIC101.PV", "items": [
        *items((NOW - 2, 1.5), (NOW - 1, 2.0), (NOW, 3.0)),  # two conflicts, one new
        {"timestamp": NOW - 2, "value": 1.0, "good": False},  # a duplicate in the batch
    ]}])
    assert report.tags[0].refused == {"duplicate_in_batch": 1, "conflict": 2}
    assert (report.stored, report.already_stored, report.partial) == (1, 0, True)
    assert stored(plant_store) == [
        ("FIC101.PV", NOW - 2, 1.0, True),
        ("FIC101.PV", NOW - 1, None, False),
        ("FIC101.PV", NOW, 3.0, True),
    ]
    assert balanced(report)


def test_out_of_order_items_are_counted_and_stored_sorted(plant_store: Store) -> None:
    report = ingest(plant_store, [{"tag": "FIC101.PV", "items": items(
        (NOW - 1, 1.0), (NOW - 3, 3.0), (NOW, 0.0), (NOW - 2, 2.0)
    )}])
    assert (report.out_of_order, report.stored, report.partial) == (2, 4, False)
    assert [t for t, _, _ in report.new_samples["FIC101.PV"]] == [NOW - 3, NOW - 2, NOW - 1, NOW]
    assert len(stored(plant_store)) == 4


def test_large_batches_go_in_few_statements(plant_store: Store) -> None:
    statements: list[int] = []

    def record(conn: Any, cursor: Any, statement: str, parameters: Any, *_: Any) -> None:
        if statement.startswith("INSERT INTO samples"):
            statements.append(len(parameters))

    n = 2 * INSERT_CHUNK + 10
    event.listen(plant_store.engine, "before_cursor_execute", record)
    try:
        report = ingest(plant_store, [
            {"tag": "FIC101.PV", "items": items(*((NOW - i, float(i)) for i in range(n)))},
            {"tag": "FIC101.OP", "items": items((NOW, 1.0))},
        ])
    finally:
        event.remove(plant_store.engine, "before_cursor_execute", record)
    assert report.stored == n + 1 == len(stored(plant_store))
    if plant_store.engine.dialect.name == "postgresql":
        assert statements == [0]  # COPY into a stage table, then one INSERT ... SELECT
    else:
        assert statements == [4 * INSERT_CHUNK, 4 * INSERT_CHUNK, 4 * 11]  # 4 columns a row


def test_a_row_written_by_another_writer_meanwhile_is_accounted_for(plant_store: Store) -> None:
    """Between the look-up and the INSERT another connection stores the same times."""

    def other_writer(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        if statement.startswith("INSERT INTO samples") and not conn.info.get("other"):
            with plant_store.engine.connect() as other:
                other.info["other"] = True
                other.execute(insert(Sample), [
                    {"tag": "FIC101.PV", "time": NOW - 1, "value": 1.0, "good": True},
                    {"tag": "FIC101.PV", "time": NOW, "value": 9.0, "good": True},
                ])
                other.commit()

    event.listen(plant_store.engine, "before_cursor_execute", other_writer)
    try:
        report = ingest(plant_store, [{"tag": "FIC101.PV", "items": items(
            (NOW - 2, 0.0), (NOW - 1, 1.0), (NOW, 2.0)
        )}])
    finally:
        event.remove(plant_store.engine, "before_cursor_execute", other_writer)
    tag = report.tags[0]
    assert (tag.stored, tag.already_stored, tag.refused) == (1, 1, {"conflict": 1})
    assert report.new_samples == {"FIC101.PV": [(NOW - 2, 0.0, True)]}
    assert stored(plant_store)[-1] == ("FIC101.PV", NOW, 9.0, True)
    assert balanced(report)


@pytest.mark.parametrize(
    ("batch", "where"),
    [
        ([{"items": []}], "batch[0].tag: Field required"),
        ([{"tag": "", "items": []}], "batch[0].tag: String should have at least 1 character"),
        ([{"tag": "FIC101.PV", "items": [{"timestamp": True, "value": 1.0}]}],
         "batch[0].items[0].timestamp"),
        ([{"tag": "FIC101.PV", "items": [{"timestamp": NOW, "value": 1, "quality": 0}]}],
         "batch[0].items[0].quality: Extra inputs are not permitted"),
        ({"tag": "FIC101.PV"}, "batch[0]"),
        (5, "expected a list of {tag, items} objects"),
    ],
)
def test_a_batch_of_the_wrong_shape_is_refused_with_the_place(
    plant_store: Store, batch: Any, where: str
) -> None:
    with pytest.raises(IngestError, match="invalid batch") as error:
        ingest(plant_store, batch)
    assert where in str(error.value)
    assert stored(plant_store) == []


# ---------------------------------------------------------------- the invariant


TIMES = [NOW - 3, NOW - 2, NOW - 1.5, NOW]
stamps = st.one_of(
    st.sampled_from(TIMES),
    st.sampled_from(TIMES).map(lambda t: f"{t:.1f}"),
    st.just("2024-05-01T12:00:00Z"),  # == NOW, to collide with the numeric form
    st.sampled_from(["", "soon", "nan"]),
    st.just(NOW + 3600.0),
)
item = st.fixed_dictionaries(
    {"timestamp": stamps,
     "value": st.sampled_from([0.0, 1.5, -2.0, None, math.nan, math.inf])},
    optional={"good": st.booleans()},
)
batches = st.lists(
    st.fixed_dictionaries({
        "tag": st.sampled_from(["FIC101.PV", "FIC101.OP", "TIC999.PV"]),
        "items": st.lists(item, max_size=8),
    }),
    max_size=4,
)


def expected_store(
    store_before: dict[tuple[str, float], tuple[float | None, bool]], batch: list[dict[str, Any]]
) -> dict[tuple[str, float], tuple[float | None, bool]]:
    """The store after ``batch``, by the rules: first item of a time wins, stored rows stay."""
    after = dict(store_before)
    seen: set[tuple[str, float]] = set()
    for entry in batch:
        for it in entry["items"]:
            time = parse_timestamp(it["timestamp"])
            if entry["tag"] not in KNOWN or time is None or time > NOW + 300:
                continue
            key = (entry["tag"], time)
            if key in seen:
                continue
            seen.add(key)
            value = it["value"]
            good = it.get("good", True) and value is not None and math.isfinite(value)
            after.setdefault(key, (value if good else None, good))
    return after


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(first=batches, second=batches)
def test_every_item_is_accounted_for_and_the_store_follows_the_rules(
    plant_store: Store, first: list[dict[str, Any]], second: list[dict[str, Any]]
) -> None:
    with plant_store.session() as session:
        session.execute(delete(Sample))
    model: dict[tuple[str, float], tuple[float | None, bool]] = {}
    rows: list[Row] = []
    for batch in (first, second):
        model = expected_store(model, batch)
        report = ingest(plant_store, batch)
        assert balanced(report)
        assert report.received == sum(len(entry["items"]) for entry in batch)
        assert report.partial == bool(report.refused)
        rows = stored(plant_store)
        assert rows == sorted((tag, t, v, g) for (tag, t), (v, g) in model.items())
        assert sum(len(s) for s in report.new_samples.values()) == report.stored
    again = ingest(plant_store, second)
    assert again.stored == 0 and stored(plant_store) == rows


# ---------------------------------------------------------------- CSV


def test_long_csv_with_quality_in_any_column_order(plant_store: Store) -> None:
    report = upload(plant_store, (
        "\ufeffValue,Tag,Timestamp,Good\n"
        "10.5,FIC101.PV,2024-05-01T12:00:00Z,true\n"
        ",FIC101.PV,2024-05-01T11:59:59Z,\n"
        "41,FIC101.OP,1714564800,0\n"
        "\n"
        "nan,FIC101.OP,1714564799,good\n"
        "1,TIC999.PV,1714564799,good\n"
    ))
    assert stored(plant_store) == [
        ("FIC101.OP", NOW - 1, None, False),
        ("FIC101.OP", NOW, None, False),
        ("FIC101.PV", NOW - 1, None, False),
        ("FIC101.PV", NOW, 10.5, True),
    ]
    assert (report.received, report.stored, report.bad) == (5, 4, 3)
    assert report.refused == {"unknown_tag": 1}


def test_wide_csv_with_a_blank_cell_and_a_bad_timestamp(plant_store: Store) -> None:
    report = upload(plant_store, (
        "time,FIC101.PV,FIC101.OP\n"
        "1714564798,10.0,40.0\n"
        "1714564799,,41.0\n"
        "1714564800,NA,42.0\n"
        "noon,11.0,43.0\n"
    ))
    pv, op = report.tags
    assert (pv.received, pv.stored, pv.bad, pv.refused) == (3, 2, 1, {"bad_timestamp": 1})
    assert (op.received, op.stored, op.refused) == (4, 3, {"bad_timestamp": 1})
    assert [row[1:3] for row in stored(plant_store) if row[0] == "FIC101.PV"] == [
        (NOW - 2, 10.0), (NOW, None)
    ]
    assert balanced(report)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "CSV: the upload is empty"),
        ("time,FIC101.PV\n1,2\n3\n", "CSV row 3: 1 cells, the header has 2"),
        ("time,FIC101.PV\n1,2\n3,high\n", "CSV row 3, column 'FIC101.PV': 'high' is not a number"),
        ("tag,timestamp,value\nFIC101.PV,1,x1\n",
         "CSV row 2, column 'value': 'x1' is not a number"),
        ("tag,timestamp,value,good\nFIC101.PV,1,1,maybe\n",
         "CSV row 2, column 'good': 'maybe' is not true/false"),
        ("tag,timestamp,value\n ,1,1\n", "CSV row 2, column 'tag': empty tag"),
        ("tag,timestamp,value,unit\n", "CSV row 1, column 4: unexpected column 'unit'"),
        ("tag,time,timestamp,value\n", "CSV row 1, column 3: a second timestamp column"),
        ("tag,timestamp\n", "CSV row 1: the long format needs a value column"),
        ("FIC101.PV,FIC101.OP\n1,2\n", "CSV row 1, column 1: 'FIC101.PV' is not a time column"),
        ("time\n1\n", "CSV row 1: the wide format needs at least one tag column"),
        ("time,FIC101.PV,FIC101.PV\n", "CSV row 1, column 3: duplicate column 'FIC101.PV'"),
        ("time,,FIC101.PV\n", "CSV row 1, column 2: empty column name"),
        ('time,FIC101.PV\n1,"2\n', "CSV line 2: not valid CSV: unexpected end of data"),
    ],
)
def test_malformed_csv_is_refused_with_row_and_column(
    plant_store: Store, text: str, message: str
) -> None:
    with pytest.raises(IngestError) as error:
        upload(plant_store, text)
    assert str(error.value).startswith(message)
    assert stored(plant_store) == []


# ---------------------------------------------------------------- retention


def test_purge_deletes_only_older_samples(plant_store: Store) -> None:
    ingest(plant_store, [{"tag": "FIC101.PV", "items": items(*((NOW - i, 1.0) for i in range(10)))}
    ])
    with plant_store.session() as session:
        assert purge_samples(session, NOW - 4) == 5
    assert [row[1] for row in stored(plant_store)] == [NOW - i for i in range(4, -1, -1)]
    with pytest.raises(ValueError, match="finite"), plant_store.session() as session:
        purge_samples(session, math.nan)


def test_a_batch_of_many_tags_is_compared_with_the_store_tag_by_tag(store):
    """The samples already stored are read for many tags at once (TAGS_PER_LOOKUP per
    statement): every tag's items are still compared with its own samples only."""
    tags = [f"T{k:03d}.PV" for k in range(2 * TAGS_PER_LOOKUP + 5)]
    batch = [{"tag": tag, "items": items((NOW - 10 - k, float(k)), (NOW - k, 1.0))}
             for k, tag in enumerate(tags)]
    with store.session() as session:
        first = ingest_batch(session, batch, known_tags=set(tags), now=NOW)
    assert (first.stored, first.already_stored) == (2 * len(tags), 0)
    batch[-1]["items"][1]["value"] = 2.0  # the last tag's second sample changed
    batch[0]["items"].append({"timestamp": NOW + 1, "value": 3.0})  # one new sample
    with store.session() as session:
        again = ingest_batch(session, batch, known_tags=set(tags), now=NOW)
    assert (again.stored, again.already_stored) == (1, 2 * len(tags) - 1)
    assert {t.tag: t.refused for t in again.tags if t.refused} == {tags[-1]: {"conflict": 1}}

"""Rolling buffers: the ring buffer itself, and loop windows from ingested and stored samples."""

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analytics.quality import assess_quality
from service.buffer import CAPACITY_MARGIN, LoopBuffers, LoopWindowData, RingBuffer
from service.config import LoopConfig, PlantConfig
from service.ingest import ingest_batch
from service.plant import sync_plant
from service.store.db import Store

NOW = 1_714_564_800.0  # 2024-05-01T12:00:00Z, a multiple of every ts below
HORIZON = 600.0
PLANT = PlantConfig.model_validate({"loops": [
    {"id": "FIC-101", "tags": {"op": "FIC101.OP", "pv": "FIC101.PV", "sp": "FIC101.SP"},
     "ts": 1.0},
    {"id": "LIC-201", "tags": {"pv": "LIC201.PV"}, "ts": 5.0},
]})


def assert_same(a: np.ndarray[Any, Any] | None, b: np.ndarray[Any, Any] | None) -> None:
    assert a is not None and b is not None
    np.testing.assert_array_equal(a, b)  # NaN == NaN here


# ---------------------------------------------------------------- RingBuffer


def test_capacity_follows_horizon_and_ts_and_memory_is_reported() -> None:
    buffer = RingBuffer(horizon_s=3600.0, ts=1.0)
    assert buffer.capacity == math.ceil(3600 * CAPACITY_MARGIN) + 1
    assert buffer.nbytes == 16 * buffer.capacity  # float64 time and value
    assert len(buffer) == 0


def test_appends_in_order_wrap_around_and_keep_the_horizon() -> None:
    buffer = RingBuffer(horizon_s=10.0, ts=1.0)
    capacity = buffer.capacity
    for start in range(0, 50, 5):  # batches of five, 50 samples in all
        times = np.arange(start, start + 5, dtype=float)
        buffer.append(times, times * 2)
    assert buffer.capacity == capacity and len(buffer) == capacity
    t, v = buffer.samples()
    np.testing.assert_array_equal(t, np.arange(50 - capacity, 50))
    np.testing.assert_array_equal(v, 2 * t)
    t, v = buffer.between(40.0, 42.0)
    np.testing.assert_array_equal(t, [40.0, 41.0, 42.0])


def test_a_late_sample_is_inserted_in_order_and_a_resent_time_replaced() -> None:
    buffer = RingBuffer(horizon_s=100.0, ts=1.0)
    buffer.append([0.0, 1.0, 3.0, 4.0], [0.0, 1.0, 3.0, 4.0])
    buffer.append([2.0, 4.0], [2.0, np.nan])
    t, v = buffer.samples()
    np.testing.assert_array_equal(t, [0.0, 1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(v, [0.0, 1.0, 2.0, 3.0, np.nan])


def test_a_tag_sampled_faster_than_ts_grows_rather_than_lose_its_horizon() -> None:
    buffer = RingBuffer(horizon_s=10.0, ts=1.0)
    times = np.arange(0.0, 100.0, 0.25)
    for chunk in np.split(times, 40):
        buffer.append(chunk, chunk)
    t, _ = buffer.between(90.0 - 1e-9, 100.0)
    np.testing.assert_array_equal(t, np.arange(90.0, 100.0, 0.25))
    assert buffer.capacity >= 40


def test_bad_input_is_refused() -> None:
    buffer = RingBuffer(horizon_s=10.0, ts=1.0)
    with pytest.raises(ValueError, match="3 times but 2 values"):
        buffer.append([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="finite"):
        buffer.append([1.0, np.nan], [1.0, 2.0])
    with pytest.raises(ValueError, match="positive"):
        RingBuffer(horizon_s=10.0, ts=0.0)


@settings(max_examples=200, deadline=None)
@given(st.lists(
    st.lists(st.integers(min_value=0, max_value=60), max_size=15), max_size=12
))
def test_the_buffer_holds_exactly_what_a_plain_dict_would_within_the_horizon(
    batches: list[list[int]],
) -> None:
    """Random batches, in and out of order, with repeats: compare with a reference."""
    buffer = RingBuffer(horizon_s=10.0, ts=1.0)
    reference: dict[float, float] = {}
    for k, batch in enumerate(batches):
        times = np.array(batch, dtype=float)
        buffer.append(times, times + 1000.0 * k)
        reference.update({float(t): float(t) + 1000.0 * k for t in batch})
    if not reference:
        assert len(buffer) == 0
        return
    newest = max(reference)
    t, v = buffer.samples()
    assert np.all(np.diff(t) > 0) and t[-1] == newest
    inside = t >= newest - 10.0
    assert dict(zip(t[inside].tolist(), v[inside].tolist(), strict=True)) == {
        time: value for time, value in reference.items() if time >= newest - 10.0
    }


# ---------------------------------------------------------------- LoopBuffers and the store


@pytest.fixture
def plant_store(store: Store) -> Store:
    """The store with the plant's loops and tags."""
    with store.session() as session:
        sync_plant(session, PLANT, NOW)
    return store


def push(store: Store, buffers: LoopBuffers, batch: list[dict[str, Any]]) -> None:
    """Ingest as the API does: commit, then hand the new samples to the buffers."""
    with store.session() as session:
        report = ingest_batch(session, batch, known_tags=buffers.tags, now=NOW)
    buffers.append_new(report.new_samples)


def series(tag: str, times: np.ndarray[Any, Any], values: np.ndarray[Any, Any]) -> dict[str, Any]:
    items = [{"timestamp": float(t), "value": float(v)} for t, v in zip(times, values, strict=True)]
    return {"tag": tag, "items": items}


def test_a_window_aligns_signals_stamped_almost_together(plant_store: Store) -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    t = NOW - np.arange(299, -1, -1, dtype=float)
    push(plant_store, buffers, [
        series("FIC101.OP", t + 0.02, np.sin(t)),  # stamped 20 ms after the grid
        series("FIC101.PV", t - 0.3, np.cos(t)),  # 300 ms before: still within ts/2
        series("FIC101.SP", t[::10], np.full(30, 50.0)),  # only every 10 s
    ])
    window = buffers.window("FIC-101", 120.0, NOW)
    assert window.ts == 1.0 and window.mv is None
    np.testing.assert_array_equal(window.t, NOW - np.arange(119, -1, -1))
    assert_same(window.op, np.sin(window.t))
    assert_same(window.pv, np.cos(window.t))
    expected_sp = np.where((NOW - window.t) % 10 == 9, 50.0, np.nan)  # sent at NOW - 9 - 10k
    assert_same(window.sp, expected_sp)
    assert set(window.signals) == {"op", "pv", "sp"}


def test_gaps_bad_samples_and_distant_stamps_are_nan_and_the_quality_screen_sees_them(
    plant_store: Store,
) -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    t = NOW - np.arange(199, -1, -1, dtype=float)
    pv = np.sin(2 * np.pi * t / 40.0)
    keep = np.ones(t.size, dtype=bool)
    keep[50:60] = False  # a ten-sample gap: nothing was sent
    pv_batch = series("FIC101.PV", t[keep], pv[keep])
    for item in pv_batch["items"][100:105]:
        item["good"] = False  # flagged bad by the historian
    late = series("FIC101.OP", t[::2] + 0.6, pv[::2])  # every 2 s, stamped 0.6 s late
    push(plant_store, buffers, [pv_batch, late])

    window = buffers.window("FIC-101", 200.0, NOW)
    assert window.pv is not None and window.op is not None and window.sp is not None
    holes = np.flatnonzero(np.isnan(window.pv))
    np.testing.assert_array_equal(holes, [*range(50, 60), *range(110, 115)])
    assert_same(window.pv[~np.isnan(window.pv)], pv[keep][np.r_[0:100, 105:190]])
    # a late OP sample is 0.4 s from the next grid point: it lands there; the points
    # in between are 0.6 s or more from any sample, farther than ts/2: NaN
    assert_same(window.op[1::2], pv[::2])
    assert np.isnan(window.op[::2]).all() and np.isnan(window.sp).all()

    report = assess_quality(window.t, {"pv": window.pv}, window.ts)
    assert "nonfinite" in report.codes("pv")


def test_a_restart_rebuilds_the_same_windows_from_the_store(plant_store: Store) -> None:
    before = LoopBuffers(PLANT, horizon_s=HORIZON)
    t = NOW - np.arange(899, -1, -1, dtype=float)  # 900 s: longer than the horizon
    push(plant_store, before, [
        series("FIC101.PV", t, np.sin(t)),
        series("FIC101.OP", t[::-1], np.cos(t[::-1])),  # newest first: out of order
        {"tag": "FIC101.SP", "items": [{"timestamp": NOW - 3, "value": None}]},
        series("LIC201.PV", t[4::5], t[4::5] / 100.0),  # on multiples of its ts of 5 s
    ])
    after = LoopBuffers(PLANT, horizon_s=HORIZON)
    with plant_store.session() as session:
        loaded = after.rebuild_from_store(session, NOW)
    in_horizon = t >= NOW - HORIZON
    assert loaded == 2 * in_horizon.sum() + 1 + in_horizon[4::5].sum()
    for loop_id, duration in (("FIC-101", HORIZON), ("FIC-101", 60.0), ("LIC-201", 300.0)):
        old, new = before.window(loop_id, duration, NOW), after.window(loop_id, duration, NOW)
        np.testing.assert_array_equal(old.t, new.t)
        for name in ("op", "pv", "sp", "mv"):
            a, b = getattr(old, name), getattr(new, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert_same(a, b)
    lic = after.window("LIC-201", 300.0, NOW)
    assert lic.ts == 5.0 and lic.t.size == 60
    assert lic.pv is not None and not np.isnan(lic.pv).any()


def test_a_window_is_cut_on_multiples_of_ts_before_now() -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    buffers.append("LIC201.PV", [NOW - 10.0, NOW - 5.0, NOW], [1.0, 2.0, 3.0])
    window = buffers.window("LIC-201", 12.0, NOW + 4.9)
    np.testing.assert_array_equal(window.t, [NOW - 5.0, NOW])
    assert_same(window.pv, np.array([2.0, 3.0]))


def test_appends_of_unknown_tags_and_bad_windows_are_refused() -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    with pytest.raises(KeyError, match=r"TIC999\.PV"):
        buffers.append("TIC999.PV", [NOW], [1.0])
    buffers.append_new({"TIC999.PV": [(NOW, 1.0, True)]})  # not buffered: left to the store
    with pytest.raises(KeyError, match="TIC-999"):
        buffers.window("TIC-999", 60.0, NOW)
    with pytest.raises(ValueError, match=r"at most the buffer horizon of 600\.0 s"):
        buffers.window("FIC-101", 601.0, NOW)
    with pytest.raises(ValueError, match="positive"):
        buffers.window("FIC-101", 0.0, NOW)


def test_good_flags_and_none_values_become_holes() -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    buffers.append("FIC101.PV", [NOW - 2, NOW - 1, NOW], [1.0, None, 3.0], [True, True, False])
    assert_same(buffers.window("FIC-101", 3.0, NOW).pv, np.array([1.0, np.nan, np.nan]))


def test_memory_per_loop_and_loops_changed_at_run_time() -> None:
    buffers = LoopBuffers(PLANT, horizon_s=HORIZON)
    per_tag = 16 * (math.ceil(HORIZON * CAPACITY_MARGIN) + 1)
    assert buffers.memory_bytes("FIC-101") == 3 * per_tag
    buffers.append("FIC101.PV", [NOW], [7.0])
    buffers.add_loop(LoopConfig.model_validate(
        {"id": "FIC-101", "tags": {"pv": "FIC101.PV", "mv": "FIC101.MV"}, "ts": 1.0}
    ))
    assert buffers.tags == {"FIC101.PV", "FIC101.MV", "LIC201.PV"}
    window = buffers.window("FIC-101", 1.0, NOW)
    assert isinstance(window, LoopWindowData) and window.op is None
    assert_same(window.pv, np.array([7.0]))  # the kept tag kept its samples
    assert window.mv is not None and np.isnan(window.mv).all()


def test_a_mode_reported_only_when_it_changes_holds_until_the_next_value(store: Store) -> None:
    """The mode tag of a DCS that reports changes only: each grid point takes the latest
    value (bad values skipped), before the first value none; the stored tag's signal is
    ``mode`` (migration 0005 widened the column)."""
    plant = PlantConfig.model_validate({"loops": [
        {"id": "FIC-101", "tags": {"pv": "FIC101.PV", "mode": "FIC101.MODE"},
         "mode_map": {16: "manual", 8: "auto"}, "ts": 1.0}]})
    buffers = LoopBuffers(plant, horizon_s=HORIZON)
    buffers.append("FIC101.PV", NOW - 9 + np.arange(10.0), np.arange(10.0))
    buffers.append("FIC101.MODE", [NOW - 7.2, NOW - 4.0, NOW - 2.0, NOW - 1.4],
                   [8.0, 16.0, 3.0, 8.0], good=[True, True, False, True])
    window = buffers.window("FIC-101", 10.0, NOW)
    assert_same(window.mode, np.array([np.nan, np.nan, 8, 8, 8, 16, 16, 16, 8, 8]))
    assert set(window.signals) == {"pv"}  # the measured signals only
    with store.session() as session:
        sync_plant(session, plant, NOW)
        ingest_batch(session, [{"tag": "FIC101.MODE", "items": [
            {"timestamp": NOW, "value": 16, "good": True}]}], known_tags=buffers.tags, now=NOW)
    with store.session() as session:
        assert LoopBuffers.from_store(session, plant.loops, since=NOW - 60, now=NOW).window(
            "FIC-101", 5.0, NOW).mode[-1] == 16.0

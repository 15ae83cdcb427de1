"""Tests of analytics.quality: each defect is injected with a known size and
the report must name it and measure it."""

from __future__ import annotations

import numpy as np
import pytest

from analytics.errors import DataError
from analytics.quality import QualityIssue, QualityLimits, QualityReport, assess_quality
from tests.shared_data import isdb_labels, load_isdb_loop

N = 2000
TS = 1.0


def _clean(seed: int = 0, n: int = N) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    return 50.0 + 5.0 * np.sin(2 * np.pi * k / 97.0) + 0.3 * rng.standard_normal(n)


def _issue(report: QualityReport, code: str, signal: str | None = None) -> QualityIssue:
    found = [i for i in report.issues if i.code == code and (signal is None or i.signal == signal)]
    assert found, f"no '{code}' issue for {signal!r}; issues: {report.issues}"
    return found[0]


def _deadband_compress(x: np.ndarray, deviation: float) -> tuple[np.ndarray, int]:
    """Historian-style dead-band (box-car) compression read back by linear
    interpolation: a point is archived when it leaves the band +-deviation
    around the last archived value.  Returns the reconstruction and the
    number of archived points."""
    kept = [0]
    last = x[0]
    for i in range(1, x.size - 1):
        if abs(x[i] - last) > deviation:
            kept.append(i)
            last = x[i]
    kept.append(x.size - 1)
    idx = np.asarray(kept)
    return np.interp(np.arange(x.size), idx, x[idx]), idx.size


# ----------------------------------------------------------------------------
# clean data


def test_clean_sinusoid_with_noise_is_usable_without_warnings() -> None:
    t = np.arange(N) * TS
    rep = assess_quality(t, {"op": _clean(1), "pv": _clean(2)}, ts=TS)
    assert rep.usable
    assert rep.reasons() == ()
    assert [i for i in rep.issues if i.severity != "info"] == []
    assert rep.ts == TS
    assert rep.samples == N


def test_uniform_data_without_time_stamps_uses_ts() -> None:
    rep = assess_quality(None, {"pv": _clean()}, ts=0.5)
    assert rep.usable and rep.ts == 0.5 and rep.issues == ()


# ----------------------------------------------------------------------------
# missing values


def test_injected_nan_reported_with_count() -> None:
    x = _clean()
    rng = np.random.default_rng(3)
    bad = rng.choice(N, size=37, replace=False)
    x[bad] = np.nan
    x[bad[0]] = np.inf
    rep = assess_quality(None, {"op": _clean(4), "pv": x}, ts=TS)
    issue = _issue(rep, "nonfinite", "pv")
    assert issue.value == 37
    assert "37" in issue.message
    assert issue.severity == "warning"  # 1.85 % is below the fatal fraction
    assert "op" not in {i.signal for i in rep.issues}
    assert rep.usable


def test_mostly_nan_signal_is_fatal() -> None:
    x = _clean()
    x[: int(0.3 * N)] = np.nan
    rep = assess_quality(None, {"pv": x}, ts=TS)
    issue = _issue(rep, "nonfinite", "pv")
    assert issue.value == 0.3 * N
    assert issue.severity == "fatal"
    assert not rep.usable
    assert issue.message in rep.reasons()


def test_all_nan_signal_is_unusable_not_an_exception() -> None:
    rep = assess_quality(None, {"pv": np.full(N, np.nan)}, ts=TS)
    assert not rep.usable
    assert _issue(rep, "nonfinite", "pv").value == N


# ----------------------------------------------------------------------------
# length and time stamps


def test_too_few_samples_is_fatal() -> None:
    rep = assess_quality(None, {"pv": _clean(n=40)}, ts=TS)
    assert not rep.usable
    assert _issue(rep, "too_few_samples").value == 40


def test_non_increasing_time_stamps_reported_with_index() -> None:
    t = np.arange(N, dtype=float) * TS
    t[500] = t[499] - 0.5  # step 499 -> 500 goes backwards
    rep = assess_quality(t, {"pv": _clean()}, ts=TS)
    issue = _issue(rep, "time_not_increasing", "t")
    assert issue.value == 499
    assert "499" in issue.message
    assert issue.severity == "fatal"
    assert not rep.usable


def test_duplicate_time_stamps_reported_with_index() -> None:
    t = np.arange(N, dtype=float) * TS
    t[701:] -= TS  # t[701] == t[700]
    rep = assess_quality(t, {"pv": _clean()}, ts=TS)
    issue = _issue(rep, "time_duplicate", "t")
    assert issue.value == 700
    assert issue.severity == "warning"


def test_gap_reported_with_largest_gap() -> None:
    t = np.arange(N, dtype=float) * TS
    t[1200:] += 30.0  # one 31 s step
    t[1500:] += 9.0  # one 10 s step
    rep = assess_quality(t, {"pv": _clean()})
    issue = _issue(rep, "gaps", "t")
    assert issue.value == pytest.approx(31.0)
    assert "2 gaps" in issue.message
    assert rep.ts == pytest.approx(TS)  # median step, gaps do not bias it
    assert rep.usable  # 38 s missing of ~2000 s


def test_irregular_sampling_reported() -> None:
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.6, 1.4, N))
    rep = assess_quality(t, {"pv": _clean()})
    spread = _issue(rep, "irregular_sampling", "t").value
    assert spread is not None and spread > 0.5


def test_ts_mismatch_reported() -> None:
    t = np.arange(N, dtype=float) * 2.0
    rep = assess_quality(t, {"pv": _clean()}, ts=1.0)
    assert _issue(rep, "ts_mismatch", "t").value == pytest.approx(2.0)


# ----------------------------------------------------------------------------
# frozen and constant signals


def test_constant_signal_unusable_with_reason() -> None:
    rep = assess_quality(None, {"op": _clean(), "pv": np.full(N, 12.5)}, ts=TS)
    assert not rep.usable
    issue = _issue(rep, "constant", "pv")
    assert issue.severity == "fatal"
    assert len(rep.reasons()) == 1
    assert "pv" in rep.reasons()[0] and "constant" in rep.reasons()[0]


def test_frozen_segment_reported_with_run_length() -> None:
    x = _clean()
    x[800:1100] = x[800]  # transmitter frozen for 300 samples
    rep = assess_quality(None, {"pv": x}, ts=TS)
    issue = _issue(rep, "flatline", "pv")
    assert issue.value == 300
    assert "800" in issue.message
    assert issue.severity == "warning"


# ----------------------------------------------------------------------------
# saturation


def _saturated_op() -> np.ndarray:
    rng = np.random.default_rng(6)
    op = 70.0 + 10.0 * np.sin(2 * np.pi * np.arange(N) / 150.0) + rng.standard_normal(N)
    op[200:500] = 100.0  # 3 blocks, 600 samples = 30 %
    op[900:1100] = 100.0
    op[1600:1700] = 100.0
    return op


def test_op_saturated_at_100_for_30_percent() -> None:
    rep = assess_quality(None, {"op": _saturated_op(), "pv": _clean()}, ts=TS)
    issue = _issue(rep, "saturation", "op")
    assert issue.value == pytest.approx(0.30, abs=1e-9)
    assert "upper" in issue.message
    assert issue.severity == "warning"
    # The runs at the limit are saturation, not a frozen transmitter.
    assert "flatline" not in rep.codes("op")


def test_saturation_against_known_range() -> None:
    op = _saturated_op()
    op[op >= 100.0] = 99.8  # within 0.5 % of the range end
    rep = assess_quality(None, {"op": op}, ts=TS, ranges={"op": (0.0, 100.0)})
    assert _issue(rep, "saturation", "op").value == pytest.approx(0.30, abs=0.01)


def test_quantised_signal_visiting_its_extremes_is_not_saturation() -> None:
    x = np.round(np.sin(2 * np.pi * np.arange(N) / 100.0) / 0.25) * 0.25
    rep = assess_quality(None, {"pv": x}, ts=TS)
    assert "saturation" not in rep.codes()


# ----------------------------------------------------------------------------
# quantisation and compression


def test_quantised_signal_reports_resolution() -> None:
    rng = np.random.default_rng(7)
    k = np.arange(N)
    x = 1.2 * np.sin(2 * np.pi * k / 80.0) + 0.2 * rng.standard_normal(N)
    xq = np.round(x / 0.5) * 0.5
    rep = assess_quality(None, {"pv": xq}, ts=TS)
    issue = _issue(rep, "quantisation", "pv")
    assert issue.value == pytest.approx(0.5)  # the step that was applied
    assert issue.severity == "warning"
    # Repeated values caused by quantisation are not historian compression.
    assert "compression" not in rep.codes()
    # The unquantised signal is fine.
    assert "quantisation" not in assess_quality(None, {"pv": x}, ts=TS).codes()


def test_slow_quantised_signal_is_not_mistaken_for_compression() -> None:
    """Long runs of one level come from the quantisation, not from a
    historian's repeated-value interpolation."""
    rng = np.random.default_rng(10)
    x = 1.2 * np.sin(2 * np.pi * np.arange(N) / 400.0) + 0.05 * rng.standard_normal(N)
    rep = assess_quality(None, {"pv": np.round(x / 0.5) * 0.5}, ts=TS)
    assert rep.codes() == {"quantisation"}


def test_two_level_signal_is_fatal_quantisation() -> None:
    x = np.where(np.sin(np.arange(N) / 10.0) > 0, 1.0, 0.0)
    rep = assess_quality(None, {"op": x}, ts=TS)
    assert _issue(rep, "quantisation", "op").severity == "fatal"
    assert not rep.usable


def test_compressed_signal_reports_compression_factor() -> None:
    rng = np.random.default_rng(8)
    k = np.arange(N)
    x = 50 + 5.0 * np.sin(2 * np.pi * k / 300.0) + np.cumsum(0.05 * rng.standard_normal(N))
    xc, kept = _deadband_compress(x, deviation=0.6)
    true_cf = N / kept
    assert true_cf > 5  # the compressor really compressed
    rep = assess_quality(None, {"pv": xc}, ts=TS)
    issue = _issue(rep, "compression", "pv")
    assert issue.value == pytest.approx(true_cf, rel=0.1)
    # The uncompressed signal is not flagged.
    assert "compression" not in assess_quality(None, {"pv": x}, ts=TS).codes()


def test_compressed_archive_with_rounded_values_still_detected() -> None:
    rng = np.random.default_rng(9)
    k = np.arange(N)
    x = 20 + 3.0 * np.sin(2 * np.pi * k / 250.0) + 0.2 * rng.standard_normal(N)
    xc, kept = _deadband_compress(x, deviation=0.5)
    xc = np.round(xc, 3)  # archive read back with 3 decimals
    rep = assess_quality(None, {"pv": xc}, ts=TS)
    assert _issue(rep, "compression", "pv").value == pytest.approx(N / kept, rel=0.25)


def test_heavy_compression_is_fatal() -> None:
    k = np.arange(N)
    x = np.sin(2 * np.pi * k / 400.0)
    xc, kept = _deadband_compress(x, deviation=0.3)
    rep = assess_quality(None, {"pv": xc}, ts=TS)
    assert N / kept > 10
    assert _issue(rep, "compression", "pv").severity == "fatal"
    assert not rep.usable


def test_limits_are_configurable() -> None:
    x = _clean()
    x[800:1100] = x[800]
    rep = assess_quality(None, {"pv": x}, ts=TS, limits=QualityLimits(flat_min_run=400))
    assert "flatline" not in rep.codes()


# ----------------------------------------------------------------------------
# structurally invalid calls raise


def test_mismatched_lengths_raise_naming_signals() -> None:
    with pytest.raises(DataError, match=r"'pv' has 1999 samples but signal 'op' has 2000"):
        assess_quality(None, {"op": _clean(), "pv": _clean()[:-1]}, ts=TS)


def test_time_length_mismatch_raises() -> None:
    with pytest.raises(DataError, match=r"'t' have 10 samples"):
        assess_quality(np.arange(10.0), {"op": _clean()}, ts=TS)


def test_no_signal_or_no_time_base_raises() -> None:
    with pytest.raises(DataError):
        assess_quality(None, {}, ts=TS)
    with pytest.raises(DataError):
        assess_quality(None, {"pv": _clean()})
    with pytest.raises(DataError):
        assess_quality(None, {"pv": np.zeros((10, 2))}, ts=TS)


def test_data_error_is_a_value_error() -> None:
    with pytest.raises(ValueError):
        assess_quality(None, {"pv": _clean()}, ts=-1.0)


# ----------------------------------------------------------------------------
# real plant data (International Stiction Data Base, 14 loops)


def test_isdb_loops_are_usable() -> None:
    """The 14 curated benchmark loops must not be rejected (no false alarms)."""
    rejected = {}
    for row in isdb_labels():
        t, op, pv = load_isdb_loop(row["loop"])
        rep = assess_quality(t, {"op": op, "pv": pv}, ts=float(row["ts_s"]))
        if not rep.usable:
            rejected[row["loop"]] = rep.reasons()
        assert rep.samples == t.size
    assert rejected == {}


def test_a_sticky_valves_held_position_is_not_mistaken_for_a_frozen_or_compressed_mv() -> None:
    from analytics.synthetic_cases import synthetic_library

    case = {c.name: c for c in synthetic_library(3600)}["flow-kano-S4-J2-ts1"]
    run = case.simulate()
    op, pv, mv = run.op[0], run.pv[0], run.mv[0]
    as_pv = assess_quality(None, {"op": op, "pv": mv}, ts=1.0)
    assert {"flatline", "compression"} & set(as_pv.codes())  # the held stretches are there
    report = assess_quality(None, {"op": op, "pv": pv, "mv": mv}, ts=1.0)
    assert report.usable, report.reasons()
    assert not [i for i in report.issues if i.signal == "mv"]

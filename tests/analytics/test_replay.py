"""The fitted stiction model replayed on the measured OP (``analytics/replay.py``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from analytics.lti import TransferFunction
from analytics.replay import (
    MODEL_CYCLES_KEPT,
    MODEL_DECIMALS,
    MODEL_POINTS,
    ModelTrace,
    stiction_model_path,
)
from analytics.synthetic_cases import synthetic_library
from analytics.valves import ChoudhuryValve, KanoValve


def sticky_flow_loop() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """OP, MV, PV and ts of the synthetic library's flow loop with a Kano valve (S 4, J 2)."""
    case = next(c for c in synthetic_library(3600) if c.name == "flow-kano-S4-J2-ts1")
    run = case.simulate()
    return run.op[0], run.mv[0], run.pv[0], run.dt


TRUE_FLOW_PROCESS = TransferFunction.fopdt(1.2, 8.0, 2.0)
"""The process of ``flow-kano-S4-J2-ts1`` (analytics.synthetic_cases)."""


def test_model_path_is_the_valve_simulation_started_at_an_op_maximum():
    """With the true valve and process, the replayed MV is the simulator's MV and the
    predicted PV explains the measured one up to its measurement noise (0.2 % sd)."""
    op, mv, pv, ts = sticky_flow_loop()
    path = stiction_model_path(op, pv, ts, valve=KanoValve(4.0, 2.0),
                               process=TRUE_FLOW_PROCESS, period_s=100.0, label="true")
    assert np.isnan(path.mv[:path.start]).all() and np.isnan(path.pv[:path.start]).all()
    first = path.start // 100 * 100  # a maximum of one of the first three periods
    assert path.start < 300 and op[path.start] == op[first:first + 100].max()
    mismatch = np.abs(path.mv[path.start:] - mv[path.start:])
    assert np.median(mismatch) < 1e-9  # the same valve on the same OP: the same MV
    assert np.mean(mismatch > 0.1) < 0.01  # bar a few slips a sample early or late
    noise = 0.2**2 / np.var(pv[path.start:])
    assert path.r2 == pytest.approx(1.0 - noise, abs=0.02)


def test_model_path_predicts_pv_through_the_process_with_fitted_offset_and_drift():
    """An ideal valve with S = 0 passes OP on; PV = 3 + 0.01 t + G(OP - OP[start]) is
    reproduced exactly, G simulated independently by its difference equation."""
    ts, tau, K = 1.0, 5.0, 2.0
    k = np.arange(1000)
    op = 50 + 5 * np.sin(2 * np.pi * k / 100)
    a = math.exp(-ts / tau)
    start = int(np.argmax(op[:100]))
    u = op[start:] - op[start]
    lag = np.zeros(u.size)
    for i in range(1, u.size):  # ZOH FOPDT with 3 samples dead time, 1 of them the hold
        lag[i] = a * lag[i - 1] + K * (1 - a) * (u[i - 3] if i >= 3 else 0.0)
    pv = np.full(k.size, np.nan)
    pv[start:] = 3.0 + 0.01 * ts * np.arange(u.size) + lag
    pv[:start] = pv[start]
    path = stiction_model_path(op, pv, ts, valve=ChoudhuryValve(0.0, 0.0),
                               process=TransferFunction.fopdt(K, tau, 2.0),
                               period_s=100.0, label="linear")
    assert path.start == start
    np.testing.assert_allclose(path.mv[start:], op[start:])
    np.testing.assert_allclose(path.pv[start:], pv[start:], atol=1e-9)
    assert path.r2 == pytest.approx(1.0)


def test_the_trace_keeps_the_last_periods_at_most_model_points_and_round_trips():
    op, _, pv, ts = sticky_flow_loop()
    path = stiction_model_path(op, pv, ts, valve=KanoValve(4.0, 2.0),
                               process=TRUE_FLOW_PROCESS, period_s=100.0, label="m")
    trace = path.trace(op)
    last = slice(-MODEL_CYCLES_KEPT * path.period, None)
    assert trace.op == tuple(np.round(op[last], MODEL_DECIMALS))
    assert trace.mv == tuple(np.round(path.mv[last], MODEL_DECIMALS))
    assert (trace.r2, trace.label) == (path.r2, "m")
    assert ModelTrace.from_dict(json.loads(json.dumps(trace.to_dict()))) == trace
    slow = stiction_model_path(op, pv, ts, valve=KanoValve(4.0, 2.0),
                               process=TRUE_FLOW_PROCESS, period_s=500.0, label="m")
    kept = slow.trace(op)  # three periods of 500 samples: every k-th, from the start
    first = max(slow.start, op.size - 1500)
    step = math.ceil((op.size - first) / MODEL_POINTS)
    assert step > 1 and len(kept.op) <= MODEL_POINTS
    assert kept.pv == tuple(np.round(slow.pv[first::step], MODEL_DECIMALS))

"""Loop KPIs: the time they add to one analysis window, and the KPI history route.

Prints the median time (one core) of :func:`analytics.kpi.loop_kpis` on a
one-hour window at 1 s (3,600 samples: a sticky loop with set-point steps,
dead time known so the Harris index runs, a mode tag with ten minutes in
manual so the service factor runs and the manual samples are left out of the
controller's figures), the same beside the whole
:func:`service.analysis.analyse_window` it is part of, and each KPI's share.
Target: under 5 ms per window.

With ``--history``, also the KPI history route on PostgreSQL (a throw-away
cluster, as in the tests): ``GET /api/v1/loops/{id}/kpis`` over 30 days for
one loop analysed every minute (43,200 runs, each with a real ~8 kB
diagnosis), among 10,000 loops (the others with a day of hourly runs each,
240,000 rows with their KPIs only: a whole month for every loop would be
7 million rows, too much for a shared benchmark machine).  Target: 100 ms.
Measured on 2026-11-26 (shared 2 cores): 93 ms for the default 1,000-run
limit (982 returned), 68 ms for 500; most of it is PostgreSQL parsing each
returned run's ~8 kB ``json`` result to extract ``kpis`` (a ``jsonb`` column
or a KPI column would need a migration).  Measured again with the mode tag in
the window, while the machine ran at a load of 10 on its 2 cores: KPIs 1.18 ms
(service factor 0.03 ms), analyse_window 140 ms (the load: 50 ms before),
history 328 ms (1,000 limit) and 216 ms (500) -- to be measured again on a
quiet machine.

Migration 0007 (the run's ``kpis`` in a column of its own, a partial index of
the ``ok`` runs on ``(loop_id, started_at, id)``) and one query that counts
and thins on that index: run after the code before it, alternately, twice
each, on 2026-11-26 at a load of 3 on the 2 shared cores (the same fill, then
``VACUUM ANALYZE`` for both, as autovacuum would): history 107, 101, 155 and
100 ms before, 76, 75, 113 and 84 ms after (500 points: 99, 76, 85, 91 before;
70, 69, 85, 78 after).  The SQL alone, old and new interleaved 30 times on
one filled cluster: 75 ms median before, 51 ms after; the plan is an
index-only scan (no heap fetches) numbered and counted by two window
aggregates (about 25 ms of the 34 ms), then 982 primary-key fetches of the
chosen runs' ~0.5 kB ``kpis``, where before PostgreSQL visited and sorted
the loop's runs and decompressed and parsed each chosen run's ~9 kB result.
The rest of the route's time is Python: parsing the returned KPIs, building
and serialising the response (about 10 ms) and the in-process HTTP.  The KPIs
without a configured dead time run the ARX delay scan of
:func:`analytics.kpi.identify_dead_time` only when the window has external
excitation (set-point moves, OP moves in manual); this window has both, so
both scans run (the worst case): 5.7 ms instead of 1.24 ms, the scans
4.7 ms, measured on 2026-11-26 at a load of 6 on the 2 shared cores (a
window without set-point moves or manual skips it: the KPIs of the
healthy flow loop of the library then take 0.55 ms).

Since then (branch h24c against main, run alternately three times each on
2026-11-26 at a load of 7 on the 2 shared cores): the delay scan's Gram
matrix by the diagonal recursion (:func:`analytics.kpi._lag_gram`) instead
of stacking 39 lag columns, one valve pass and one PV noise estimate for all
the KPIs: with both scans 7.1, 11.9, 8.2 ms before and 1.56, 2.07, 1.35 ms
after (identify_dead_time 5.4, 6.8, 3.9 -> 0.67, 0.82, 0.55 ms; with a
configured dead time 1.47, 1.37, 1.46 -> 1.40, 1.63, 1.12 ms); when a scan
finds the dead time the Harris index adds its 0.27 ms.  The history route,
its KPIs passed on as the JSON text stored and, on PostgreSQL, the run ids
gathered into one array by the index-only scan and every k-th picked from
it (no window functions): 179, 212, 149 ms before, 51, 63, 27 ms after (500
points: 149, 150, 109 -> 36, 43, 22 ms).

Run with ``.venv/bin/python benchmarks/kpi.py [--history]``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the speed target says

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the project's service package, not benchmarks/service.py

import numpy as np  # noqa: E402

from analytics.kpi import (  # noqa: E402
    error_statistics,
    harris_index,
    identify_dead_time,
    loop_kpis,
    reversals_per_day,
    saturation,
    service_factor,
    setpoint_responses,
    valve_travel_per_day,
)
from analytics.synthetic_cases import synthetic_library  # noqa: E402
from service.analysis import analyse_window  # noqa: E402

T0 = 1_700_000_000.0
KEY = "kpi-benchmark-admin-key-0123456"


def median_ms(f: Callable[[], Any], repeat: int = 200) -> float:
    f()  # warm up (numba kernels compile or load from cache)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        f()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    case = {c.name: c for c in synthetic_library(3600)}["flow-kano-S4-J2-ts1"]
    sim = case.simulate()
    op, pv = sim.op[0], sim.pv[0]
    sp = sim.sp[0] + np.repeat([0.0, 5.0, 0.0, -5.0], 900)  # four set-point steps
    pv = pv + (sp - sim.sp[0])
    osc = {"detected": True, "regularity": 5.0}
    mode = np.where((np.arange(3600) >= 2400) & (np.arange(3600) < 3000), 16.0, 8.0)
    mapping = {16.0: "manual", 8.0: "auto", 4.0: "cascade"}
    total = median_ms(lambda: loop_kpis(1.0, op=op, pv=pv, sp=sp, dead_time=4,
                                        pv_limits=(10.0, 90.0), mode=mode,
                                        mode_mapping=mapping, oscillation=osc))
    print(f"loop_kpis, one hour at 1 s (3,600 samples): {total:.2f} ms median "
          f"(target < 5 ms)")
    scan = median_ms(lambda: loop_kpis(1.0, op=op, pv=pv, sp=sp, pv_limits=(10.0, 90.0),
                                       mode=mode, mode_mapping=mapping))
    print(f"  the same without a configured dead time, not oscillating (the delay scan "
          f"runs): {scan:.2f} ms")
    parts = {
        "error_statistics": lambda: error_statistics(sp, pv, 1.0, (10.0, 90.0)),
        "harris_index": lambda: harris_index(sp - pv, 4),
        "valve_travel_per_day": lambda: valve_travel_per_day(op, 1.0),
        "reversals_per_day": lambda: reversals_per_day(op, 1.0),
        "saturation": lambda: saturation(op),
        "setpoint_responses": lambda: setpoint_responses(sp, pv, 1.0),
        "service_factor": lambda: service_factor(mode, mapping, 1.0),
        "identify_dead_time": lambda: identify_dead_time(op, pv, sp, mode == 16.0),
    }
    for name, f in parts.items():
        print(f"  {name:22s} {median_ms(f):.3f} ms")
    loop = {"ts": 1.0, "ranges": {"op": [0, 100], "pv": [0, 100]},
            "process_type": "self-regulating", "process_model": {"theta": 3.0},
            "mode_map": {"16": "manual", "8": "auto", "4": "cascade"}}
    t = np.arange(3600.0)
    window = median_ms(lambda: analyse_window(loop, 1.0, t, {"op": op, "pv": pv, "sp": sp,
                                                             "mv": None, "mode": mode}),
                       repeat=20)
    print(f"analyse_window with the KPIs: {window:.1f} ms median; the KPIs are "
          f"{100 * total / window:.1f} % of it")


def history(result: dict[str, Any]) -> None:
    """Time the KPI history route on PostgreSQL (see the module docstring)."""
    from concurrent.futures import ThreadPoolExecutor

    from fastapi.testclient import TestClient
    from sqlalchemy import text

    from service.config import PlantConfig, Settings
    from service.server import build_service
    from tests.servers import postgres_server

    plant = PlantConfig.model_validate({"loops": [{
        "id": "TARGET", "ts": 1.0, "tags": {"op": "T.OP", "pv": "T.PV", "sp": "T.SP"},
        "process_model": {"type": "fopdt", "K": 1.0, "tau": 10.0, "theta": 3.0}}]})
    with postgres_server() as url:
        settings = Settings(database_url=url, api_key=KEY)
        svc = build_service(settings, plant, executor=ThreadPoolExecutor(1), clock=lambda: T0)
        start = time.perf_counter()
        with svc.state.store.engine.begin() as db:
            db.execute(text(
                "INSERT INTO loops (id, name, config, created_at, updated_at) "
                "SELECT 'L' || i, '', '{\"importance\": \"medium\"}', 0, 0 "
                "FROM generate_series(1, 10000) AS i"))
            db.execute(text(
                "INSERT INTO analysis_runs (loop_id, started_at, status, health, result, kpis, "
                "round_end) SELECT 'L' || i, :t0 - 3600 * h, 'ok', 90, CAST(:result AS json), "
                "CAST(:kpis AS json), :t0 - 3600 * h FROM generate_series(1, 10000) AS i, "
                "generate_series(0, 23) AS h"),
                {"t0": T0, "result": json.dumps({"kpis": result["kpis"]}),
                 "kpis": json.dumps(result["kpis"])})
            db.execute(text(
                "INSERT INTO analysis_runs (loop_id, started_at, status, health, result, kpis, "
                "round_end) SELECT 'TARGET', :t0 - 60 * m, 'ok', 50, CAST(:result AS json), "
                "CAST(:kpis AS json), :t0 - 60 * m FROM generate_series(0, 43199) AS m"),
                {"t0": T0, "result": json.dumps(result), "kpis": json.dumps(result["kpis"])})
        with svc.state.store.engine.connect().execution_options(
                isolation_level="AUTOCOMMIT") as db:
            # what autovacuum does to a table after inserts: statistics, and the visibility
            # map that lets the history count and thin the runs on the index alone
            db.execute(text("VACUUM ANALYZE analysis_runs"))
        print(f"PostgreSQL filled in {time.perf_counter() - start:.0f} s: 10,001 loops, "
              f"{10_000 * 24 + 43_200:,} runs")
        client = TestClient(svc.app)
        headers = {"X-API-Key": KEY}
        params = {"since": T0 - 30 * 86400, "until": T0}
        body = client.get("/api/v1/loops/TARGET/kpis", params=params, headers=headers).json()
        assert body["total"] == 43_200, body.get("total")
        ms = median_ms(lambda: client.get("/api/v1/loops/TARGET/kpis", params=params,
                                          headers=headers), repeat=15)
        print(f"KPI history of one loop over 30 days (43,200 runs, {body['count']} returned, "
              f"HTTP in process): {ms:.0f} ms median (target < 100 ms)")
        ms = median_ms(lambda: client.get("/api/v1/loops/TARGET/kpis", params={
            **params, "limit": 500}, headers=headers), repeat=15)
        print(f"  the same thinned to 500 points: {ms:.0f} ms median")
        svc.executor.shutdown()
        svc.state.store.close()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--history", action="store_true",
                        help="also time the KPI history route on PostgreSQL")
    if parser.parse_args().history:
        case = {c.name: c for c in synthetic_library(3600)}["flow-kano-S4-J2-ts1"]
        sim = case.simulate()
        main()
        history(analyse_window({"ts": 1.0, "process_model": {"theta": 3.0}, "ranges": {}},
                               1.0, np.arange(3600.0), {"op": sim.op[0], "pv": sim.pv[0],
                                                        "sp": sim.sp[0], "mv": None}))
    else:
        main()

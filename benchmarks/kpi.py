"""Loop KPIs: the time they add to one analysis window, and the KPI history route.

Prints the median time (one core) of :func:`analytics.kpi.loop_kpis` on a
one-hour window at 1 s (3,600 samples: a sticky loop with set-point steps,
dead time known so the Harris index runs), the same beside the whole
:func:`service.analysis.analyse_window` it is part of, and each KPI's share.
Target: under 5 ms per window.

Run with ``.venv/bin/python benchmarks/kpi.py``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the speed target says

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
    loop_kpis,
    reversals_per_day,
    saturation,
    setpoint_responses,
    valve_travel_per_day,
)
from analytics.synthetic_cases import synthetic_library  # noqa: E402
from service.analysis import analyse_window  # noqa: E402


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
    total = median_ms(lambda: loop_kpis(1.0, op=op, pv=pv, sp=sp, dead_time=4,
                                        pv_limits=(10.0, 90.0), oscillation=osc))
    print(f"loop_kpis, one hour at 1 s (3,600 samples): {total:.2f} ms median "
          f"(target < 5 ms)")
    parts = {
        "error_statistics": lambda: error_statistics(sp, pv, 1.0, (10.0, 90.0)),
        "harris_index": lambda: harris_index(sp - pv, 4),
        "valve_travel_per_day": lambda: valve_travel_per_day(op, 1.0),
        "reversals_per_day": lambda: reversals_per_day(op, 1.0),
        "saturation": lambda: saturation(op),
        "setpoint_responses": lambda: setpoint_responses(sp, pv, 1.0),
    }
    for name, f in parts.items():
        print(f"  {name:22s} {median_ms(f):.3f} ms")
    loop = {"ts": 1.0, "ranges": {"op": [0, 100], "pv": [0, 100]},
            "process_type": "self-regulating", "process_model": {"theta": 3.0}}
    t = np.arange(3600.0)
    window = median_ms(lambda: analyse_window(loop, 1.0, t, {"op": op, "pv": pv, "sp": sp,
                                                             "mv": None}), repeat=20)
    print(f"analyse_window with the KPIs: {window:.1f} ms median; the KPIs are "
          f"{100 * total / window:.1f} % of it")


if __name__ == "__main__":
    main()

"""Foundation benchmarks: valve models and closed-loop simulation (issue targets in brackets).

Prints the median and spread of repeated runs after a warm-up (numba compiles
on first call; compile time is reported separately). Run with
``.venv/bin/python benchmarks/foundation.py``. The machine is shared: quote
medians and ratios from one run.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import numpy as np

from analytics.describing import df_curve
from analytics.scenarios import chapter4, column3x3
from analytics.valves import (
    ChoudhuryValve,
    DeadbandValve,
    HeValve,
    KanoValve,
    KarnoppValve,
    StenmanValve,
)

REPEATS = 15


def measure(label: str, run: Callable[[], object], target_ms: float | None = None) -> None:
    start = time.perf_counter()
    run()
    first = time.perf_counter() - start
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    median = statistics.median(times) * 1e3
    target = (
        f"  [target < {target_ms:g} ms: {'met' if median < target_ms else 'MISSED'}]"
        if target_ms
        else ""
    )
    print(
        f"{label:48s} median {median:9.2f} ms  (min {min(times) * 1e3:8.2f}, "
        f"max {max(times) * 1e3:8.2f}; first call {first * 1e3:8.1f} ms){target}"
    )


def main() -> None:
    rng = np.random.default_rng(0)
    op = 50.0 + np.cumsum(rng.normal(0.0, 0.3, 1_000_000))
    print(f"valve models over {op.size:,} OP samples (one core):")
    measure("He (fs=3, fd=1)", lambda: HeValve(3.0, 1.0).simulate(op), target_ms=20)
    for valve in (
        StenmanValve(2.0),
        DeadbandValve(2.0),
        ChoudhuryValve(4.0, 2.0),
        KanoValve(4.0, 2.0),
    ):
        measure(repr(valve), lambda valve=valve: valve.simulate(op))
    karnopp = KarnoppValve(2.0, 1.5, fv=0.05)
    measure(f"{karnopp!r} (dt=1 s, 10^5 samples)", lambda: karnopp.simulate(op[:100_000], dt=1.0))

    print("\nclosed-loop simulation, 100,000 samples:")
    single = chapter4(sticky=True)
    measure(
        "single loop (chapter 4, He valve)",
        lambda: single.run(duration=99_999 * single.dt),
        target_ms=200,
    )
    column = column3x3()
    measure(
        "3x3 column (Eq. 2.10, three He valves, noise)",
        lambda: column.run(duration=99_999 * column.dt),
        target_ms=1000,
    )

    print("\ndescribing functions, 200 amplitudes:")
    measure("analytic Choudhury DF", lambda: df_curve(ChoudhuryValve(4.0, 2.0)))
    measure("numerical He DF", lambda: df_curve(HeValve(3.0, 1.0)))


if __name__ == "__main__":
    main()

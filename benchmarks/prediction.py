"""Limit-cycle prediction and tuning advice: speed (issue 6 targets in brackets).

1. a 3x3 prediction, every solution over two decades of frequency (the column
   of thesis Eq. 2.10 under tuning 3.26) [< 1 s];
2. a 50 x 50 safe-tuning map (thesis Fig. 5.17) [< 5 s];
3. the whole single-loop advice (map, Table 5.11 actions, exact prediction and
   simulation of every candidate), for information.

Prints the median and spread of repeated runs after a warm-up (numba compiles
on first call). Run with ``make bench`` or ``.venv/bin/python benchmarks/prediction.py``.
The machine is shared: quote medians from one run.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.limit_cycle import predict_model  # noqa: E402
from analytics.lti import TransferFunction  # noqa: E402
from analytics.scenarios import chapter4, column3x3, temperature_loop  # noqa: E402
from analytics.tuning import advise, safe_tuning_map  # noqa: E402
from analytics.valves import ChoudhuryValve, KanoValve  # noqa: E402


def measure(label: str, run: Callable[[], object], repeats: int, target_s: float | None) -> None:
    """Print the median of ``repeats`` timed runs of ``run`` after one warm-up."""
    start = time.perf_counter()
    run()
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    verdict = (
        f"  [target < {target_s:g} s: {'met' if median < target_s else 'MISSED'}]"
        if target_s
        else ""
    )
    print(
        f"{label:58s} median {median:7.3f} s  (min {min(times):6.3f}, max {max(times):6.3f}; "
        f"first {first:6.3f}){verdict}"
    )


def main() -> None:
    print("3x3 prediction, every solution over two decades of frequency:")
    for sticky in ((2, 3), (1, 2, 3)):
        model = column3x3(sticky=sticky, tuning="3.26", noise_std=0.0)
        for describing in ("equivalent", "model"):
            cycles = predict_model(model, describing=describing, include_hold=False).limit_cycles
            label = f"column, valves {sticky}, {describing} DF ({len(cycles)} solutions)"
            run = partial(predict_model, model, describing=describing, include_hold=False)
            measure(label, run, repeats=5, target_s=1.0)

    print("\nsafe-tuning map, 50 x 50 tunings:")
    maps = {
        "temperature loop (FOPDT, Choudhury S=4 J=2)": (
            TransferFunction.fopdt(0.4346, 27.58, 6.0),
            ChoudhuryValve(4.0, 2.0),
            np.geomspace(0.5, 20.0, 50),
            np.geomspace(2.0, 500.0, 50),
        ),
        "level loop (integrating, Kano S=3 J=1)": (
            TransferFunction.integrating(0.02, 3.0),
            KanoValve(3.0, 1.0),
            np.geomspace(0.2, 40.0, 50),
            np.geomspace(5.0, 2000.0, 50),
        ),
        "chapter 4 loop (FOPDT, He fs=3 fd=2, numerical DF)": (
            chapter4().process,
            chapter4().loops[0].valve,
            np.geomspace(0.01, 0.2, 50),
            np.geomspace(0.2, 11.0, 50),
        ),
    }
    for label, (process, valve, kc, ti) in maps.items():
        assert isinstance(process, TransferFunction)
        mapping = partial(safe_tuning_map, process, valve, kc, ti, hold_delay=0.5)
        measure(label, mapping, repeats=5, target_s=5.0)

    print("\nsingle-loop advice (30 x 30 map, candidates predicted and simulated):")
    measure("temperature loop", lambda: advise(temperature_loop()), repeats=3, target_s=None)


if __name__ == "__main__":
    main()

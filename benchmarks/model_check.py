"""Model check (issue 8): accuracy on hidden effects, real loops, and speed.

Prints, in one run:

1. the confusion of named causes over random loops with one hidden effect
   (analytics.model_check.cases; seeds 0..N-1 per effect, N = 10 or the first
   argument), with the median held-out NMSE before and after extension;
2. what the check finds on the real loops of ../shared/data (ISDB loops,
   Jelali & Huang 2010, and the two plant loops FIC-211 and LIC-106; no
   model given, so one is identified first);
3. the median time of a check of 6,000 samples per effect [target < 10 s],
   on one core (BLAS threads pinned to 1 before numpy loads).

Run with ``.venv/bin/python benchmarks/model_check.py [N]``.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_name] = "1"

import csv  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.model_check import check_model  # noqa: E402
from analytics.model_check.cases import CATALOGUE, hidden_effect_case  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
SAMPLES = 6000
REPEATS = 5


def hidden_effects(seeds: int) -> None:
    print(f"hidden effects: {seeds} random loops per effect, {SAMPLES} samples each")
    print(f"{'hidden effect':30s} {'named':>6s}  {'NMSE before':>11s} {'after':>9s}  confusions")
    for effect in CATALOGUE:
        named: Counter[str] = Counter()
        before, after = [], []
        for seed in range(seeds):
            case = hidden_effect_case(effect, seed, SAMPLES)
            result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
            named[result.cause.effect] += 1
            before.append(result.gain.nmse_before)
            after.append(result.gain.nmse_after)
        wrong = ", ".join(f"{k} x{v}" for k, v in named.items() if k != effect)
        print(
            f"{effect:30s} {named[effect]:3d}/{seeds:<2d}  {statistics.median(before):11.3g} "
            f"{statistics.median(after):9.3g}  {wrong}"
        )


def _isdb() -> list[tuple[str, str, float, np.ndarray, np.ndarray]]:
    labels = DATA / "isdb14" / "labels.csv"
    if not labels.is_file():
        return []
    loops = []
    with labels.open(newline="") as handle:
        for row in csv.DictReader(handle):
            table = np.genfromtxt(DATA / "isdb14" / f"{row['loop']}.csv", delimiter=",", names=True)
            loops.append((row["loop"], row["label"], float(row["ts_s"]), table["OP"], table["PV"]))
    return loops


def _plant(name: str, pv_column: str, op_column: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Oldest first, the longest stretch without NULL values."""
    files = sorted((DATA / "plant_unlabelled").glob(f"{name}_*.csv"))
    if not files:
        return None
    with files[0].open(newline="", encoding="utf-8-sig") as handle:
        rows = sorted(csv.DictReader(handle), key=lambda r: (r["date"], r["time"]))
    op = np.array([np.nan if r[op_column] == "NULL" else float(r[op_column]) for r in rows])
    pv = np.array([np.nan if r[pv_column] == "NULL" else float(r[pv_column]) for r in rows])
    ok = np.concatenate([[False], np.isfinite(op) & np.isfinite(pv), [False]])
    edges = np.flatnonzero(np.diff(ok.astype(int)))
    start, stop = max(zip(edges[::2], edges[1::2], strict=True), key=lambda e: e[1] - e[0])
    print(f"  ({name}: rows {start}-{stop} of {len(rows)} used, the longest run without NULL)")
    return op[start:stop], pv[start:stop]


def real_loops() -> None:
    print("\nreal loops (no model given: identified first)")
    loops = [(name, label, ts, op, pv) for name, label, ts, op, pv in _isdb()]
    for name, pv_column, op_column in (("FIC-211", "FT_211", "FV_211"),
                                       ("LIC-106", "FT_115", "LV_106")):
        signals = _plant(name, pv_column, op_column)
        if signals is not None:
            loops.append((name, "unlabelled", 60.0, *signals))
    if not loops:
        print("  ../shared/data not found: skipped")
        return
    print(f"{'loop':8s} {'label':11s} {'samples':>7s} {'NMSE base':>9s} {'after':>7s}  "
          f"{'cause':28s} conf  measured / simulated period s")
    for name, label, ts, op, pv in loops:
        result = check_model(op, pv, ts)
        cyc = result.cycle_base
        periods = " / ".join("-" if p is None else f"{p:.0f}"
                             for p in (cyc.period_measured, cyc.period_simulated))
        print(
            f"{name:8s} {label:11s} {op.size:7d} {result.nmse_base_test:9.3g} "
            f"{result.gain.nmse_after:7.3g}  {result.cause.effect:28s} "
            f"{result.cause.confidence:4.2f}  {periods}"
        )


def speed() -> None:
    print(f"\nspeed: one check of {SAMPLES} samples, median of {REPEATS} after a warm-up")
    times_all = []
    for effect in CATALOGUE:
        case = hidden_effect_case(effect, 0, SAMPLES)

        def run(case=case) -> object:
            return check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)

        run()
        times = []
        for _ in range(REPEATS):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        times_all.extend(times)
        kind = case.base_model.process.kind
        print(f"{effect:30s} ({kind:11s}) median {statistics.median(times):6.2f} s  "
              f"(min {min(times):.2f}, max {max(times):.2f})")
    median = statistics.median(times_all)
    print(f"{'all':44s} median {median:6.2f} s  [target < 10 s: "
          f"{'met' if median < 10 else 'MISSED'}]")


def main() -> None:
    seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    hidden_effects(seeds)
    real_loops()
    speed()


if __name__ == "__main__":
    main()

"""Stiction detection and quantification: accuracy and speed.

Prints, in one run:

1. every ISDB loop (../shared/data/isdb14, Jelali & Huang 2010) with its
   label, the verdict, the confidence and each method's decision;
2. every case of the synthetic library (analytics.synthetic_cases) with the
   same, the balanced accuracy overall and per cause, and the relative
   errors of the S and J estimates against the simulated valves;
3. the median time of the detection battery and of quantification on a
   10,000-sample loop, and of the whole per-loop diagnosis on one-hour
   windows at 1 s (3,600 samples; what a plant-wide analysis pays per loop).

Run with ``make bench`` or ``.venv/bin/python benchmarks/detection.py``.
"""

from __future__ import annotations

import csv
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.diagnosis import LoopDiagnosis, diagnose_loop  # noqa: E402
from analytics.oscillation import detect_loop_oscillation  # noqa: E402
from analytics.quantification import quantify_stiction  # noqa: E402
from analytics.stiction.battery import DEFAULT_DETECTORS, run_battery  # noqa: E402
from analytics.stiction.evidence import LoopWindow  # noqa: E402
from analytics.synthetic_cases import SyntheticCase, synthetic_library  # noqa: E402
from service.loop_csv import read_loop_csv  # noqa: E402

ISDB = ROOT.parent / "shared" / "data" / "isdb14"
SHORT = {"stiction": "S", "no_stiction": "-", "undecided": "?"}


def method_columns(diagnosis: LoopDiagnosis) -> str:
    """One letter per method: S stiction, - no stiction, ? undecided, blank: not run."""
    methods = diagnosis.stiction.methods
    return " ".join(
        SHORT[methods[d.name].decision] if d.name in methods else "."
        for d in DEFAULT_DETECTORS
    )


def header() -> str:
    names = " ".join(d.name[:1] for d in DEFAULT_DETECTORS)
    return f"{'case':30s} {'label':12s} {'verdict':12s} conf  {names}"


def balanced_accuracy(pairs: Sequence[tuple[str, str]]) -> float:
    """Mean of the per-class recall over the true classes (undecided counts as wrong)."""
    recalls = []
    for label in sorted({truth for truth, _ in pairs}):
        got = [verdict for truth, verdict in pairs if truth == label]
        recalls.append(sum(v == label for v in got) / len(got))
    return float(np.mean(recalls))


def isdb() -> None:
    print("== ISDB (14 industrial loops, one fixed configuration) ==")
    print(f"methods: {', '.join(d.name for d in DEFAULT_DETECTORS)}")
    print(header())
    with (ISDB / "labels.csv").open(newline="") as handle:
        labels = list(csv.DictReader(handle))
    pairs = []
    for row in labels:
        data = read_loop_csv(ISDB / f"{row['loop']}.csv", ts=float(row["ts_s"]))
        d = diagnose_loop(ts=data.ts, op=data.op, pv=data.pv, t=data.t)
        pairs.append((row["label"], d.stiction.verdict))
        ok = "ok " if row["label"] == d.stiction.verdict else "XX "
        size = ""
        if d.quantification is not None:
            size = f"  S={d.quantification.S:.2f} J={d.quantification.J:.2f}"
        print(
            f"{ok}{row['loop']:27s} {row['label']:12s} {d.stiction.verdict:12s} "
            f"{d.stiction.confidence:.2f}  {method_columns(d)}{size}"
        )
    correct = sum(t == v for t, v in pairs)
    print(f"ISDB: {correct}/{len(pairs)} correct, balanced accuracy "
          f"{balanced_accuracy(pairs):.3f}\n")


def synthetic() -> None:
    print("== Synthetic library ==")
    print(header())
    pairs: list[tuple[str, str]] = []
    by_cause: dict[str, list[tuple[str, str]]] = defaultdict(list)
    errors_S, errors_J = [], []
    for case in synthetic_library():
        result = case.simulate()
        d = diagnose_loop(
            ts=case.ts, op=result.op[0], pv=result.pv[0], sp=result.sp[0],
            process_type=case.process_type,
        )
        pairs.append((case.label, d.stiction.verdict))
        by_cause[case.cause].append((case.label, d.stiction.verdict))
        ok = "ok " if case.label == d.stiction.verdict else "XX "
        size = ""
        q = d.quantification
        if q is not None and q.S is not None and q.J is not None and case.S and case.J:
            errors_S.append(abs(q.S - case.S) / case.S)
            errors_J.append(abs(q.J - case.J) / case.J)
            size = f"  S={q.S:.2f}/{case.S:g} J={q.J:.2f}/{case.J:g}"
        print(
            f"{ok}{case.name:27s} {case.label:12s} {d.stiction.verdict:12s} "
            f"{d.stiction.confidence:.2f}  {method_columns(d)}{size}"
        )
    print(f"synthetic: {sum(t == v for t, v in pairs)}/{len(pairs)} correct, "
          f"balanced accuracy {balanced_accuracy(pairs):.3f}")
    for cause, got in sorted(by_cause.items()):
        print(f"  {cause:22s} {sum(t == v for t, v in got)}/{len(got)}")
    if errors_S:
        print(f"quantification over {len(errors_S)} detected stiction cases: median relative "
              f"error S {statistics.median(errors_S):.1%}, J {statistics.median(errors_J):.1%}")
    print()


def timing(repeats: int = 7) -> None:
    print("== Speed on a 10,000-sample loop (CPU time of this process, median of "
          f"{repeats} runs) ==")
    case: SyntheticCase = next(c for c in synthetic_library(10_000)
                               if c.name == "flow-kano-S4-J2-ts1")
    result = case.simulate()
    op, pv = result.op[0], result.pv[0]
    osc = detect_loop_oscillation(op, pv, case.ts)
    window = LoopWindow(case.ts, op, pv, process_type=case.process_type, period_s=osc.period_s)
    run_battery(window)
    quantify_stiction(op, pv, case.ts, process_type=case.process_type, period_s=osc.period_s)
    per_method: dict[str, list[float]] = defaultdict(list)
    battery, quant, whole = [], [], []
    for _ in range(repeats):
        for detector in DEFAULT_DETECTORS:
            t0 = time.process_time()
            detector.detect(window)
            per_method[detector.name].append(time.process_time() - t0)
        t0 = time.process_time()
        run_battery(window)
        battery.append(time.process_time() - t0)
        t0 = time.process_time()
        quantify_stiction(op, pv, case.ts, process_type=case.process_type,
                          period_s=osc.period_s)
        quant.append(time.process_time() - t0)
        t0 = time.process_time()
        diagnose_loop(ts=case.ts, op=op, pv=pv, process_type=case.process_type)
        whole.append(time.process_time() - t0)
    for name, times in per_method.items():
        print(f"  {name:20s} {1e3 * statistics.median(times):7.1f} ms")
    print(f"battery (all methods)  {1e3 * statistics.median(battery):7.1f} ms  (target < 50)")
    print(f"quantification         {1e3 * statistics.median(quant):7.1f} ms  (target < 250)")
    print(f"whole pipeline         {1e3 * statistics.median(whole):7.1f} ms")


HOUR_CASES = ("flow-noise-ts1", "flow-kano-S4-J2-ts1", "flow-sine60s-ts1", "level-aggressive-ts1")


def hour_window_timing(repeats: int = 9) -> None:
    print(f"\n== Per-loop diagnosis of a one-hour window at 1 s (CPU time, median of "
          f"{repeats} runs, cases interleaved) ==")
    cases = {c.name: c for c in synthetic_library(3600)}
    signals = {}
    for name in HOUR_CASES:
        result = cases[name].simulate()
        signals[name] = (result.op[0], result.pv[0])
        diagnose_loop(ts=1.0, op=result.op[0], pv=result.pv[0])
    times: dict[str, list[float]] = defaultdict(list)
    for _ in range(repeats):
        for name, (op, pv) in signals.items():
            t0 = time.process_time()
            diagnose_loop(ts=1.0, op=op, pv=pv)
            times[name].append(time.process_time() - t0)
    medians = [statistics.median(times[name]) for name in HOUR_CASES]
    for name, median in zip(HOUR_CASES, medians, strict=True):
        print(f"  {name:24s} {1e3 * median:7.1f} ms")
    print(f"mean per loop            {1e3 * statistics.mean(medians):7.1f} ms  "
          "(10,000 loops in 10 min on 2 cores: < 120)")


if __name__ == "__main__":
    isdb()
    synthetic()
    timing()
    hour_window_timing()
